"""Argument helpers every `conav` command shares: value parsers, flags generated from config
dataclass fields, the learned agents' run flags, and the rewriting of config field names in a
library error into the flags that set them.

A config field a flag mirrors has one home: `add_fields` reads its type, default and the
comment documenting it from the dataclass, and `config_from_args` builds the config back.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import re
import tempfile
import tokenize
import typing
import warnings
from functools import cache
from pathlib import Path

# -- value parsers -------------------------------------------------------------------------------


def parse_resolution(text: str) -> tuple[int, int]:
    """`HxW` (e.g. 112x448) -> (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 112x448, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return h, w


def parse_physics_override(text: str) -> tuple[str, object]:
    """`NAME=VALUE` for a field of envs.config.PhysicsConfig, VALUE converted to the field's type."""
    from conav_jax.envs.config import PhysicsConfig

    fields = {f.name for f in dataclasses.fields(PhysicsConfig)}
    name, sep, value = text.partition("=")
    if not sep or name not in fields:
        raise argparse.ArgumentTypeError(
            f"physics override must be NAME=VALUE with NAME one of {sorted(fields)}, got {text!r}")
    kind = type(getattr(PhysicsConfig(), name))
    try:
        return name, kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"physics {name} needs a {kind.__name__}, got {value!r}") from None


def parse_names(text: str) -> tuple[str, ...]:
    """`A,B,...` -> ("A", "B", ...), blanks dropped ("" -> ())."""
    return tuple(name.strip() for name in text.split(",") if name.strip())


def parse_checkpoints(text: str | None) -> str | dict[str | None, str] | None:
    """`RUN` -> RUN; `AGENT=RUN,...` (with at most one bare RUN: the other learned agents') ->
    {agent: run, None: run}."""
    if not text or "=" not in text:
        return text
    out: dict[str | None, str] = {}
    for item in text.split(","):
        name, sep, run = item.strip().partition("=")
        name, run = (name, run) if sep else (None, name)
        if name == "" or not run or name in out:
            raise ValueError(f"--checkpoint entries look like AGENT=RUN_DIR (at most one bare RUN_DIR, each agent "
                             f"once), got {item!r}")
        out[name] = run
    return out


# -- flags from config fields --------------------------------------------------------------------


def flag(name: str) -> str:
    """The flag of a config field or keyword: `val_every` -> `--val-every`."""
    return "--" + name.replace("_", "-")


@cache
def field_docs(cls: type) -> dict[str, str]:
    """Each field of dataclass `cls` -> the comment documenting it in its source: the comment
    ending the field's line, else the comment lines right above it ("" where there is none)."""
    source = inspect.getsource(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    docs, above, line_of = {}, [], {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            owner = line_of.get(tok.start[0])
            if owner is not None:
                docs[owner] = text
            else:
                above.append(text)
        elif tok.type == tokenize.NAME and tok.start[1] == 4 and tok.string in names and tok.string not in docs:
            docs[tok.string] = " ".join(above)
            line_of[tok.start[0]] = tok.string
        elif tok.type == tokenize.NL and tok.start[1] == 0:
            above = []  # a blank line ends a comment block
        elif tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.INDENT, tokenize.DEDENT):
            if tok.type == tokenize.NEWLINE:
                above = []
    return docs


def _value_type(cls: type, name: str, default):
    """The argparse type of field `name`: the default's, else the annotation's non-None type."""
    if default is not None:
        return type(default)
    hint = typing.get_type_hints(cls)[name]
    return next((t for t in typing.get_args(hint) if t is not type(None)), hint)


def add_fields(p, cls: type, names: tuple[str, ...] | None = None, defaults=None, flags: dict | None = None,
               options: dict[str, dict] | None = None, **helps: str) -> None:
    """Add `--field-name` (or `flags[name]`) for the fields `names` of dataclass `cls` (default:
    all), each with the field's type, its default (from `defaults`, an instance, when given) and
    its documenting comment as help (`helps[name]` overrides it); `options[name]`: more
    `add_argument` keywords (choices, metavar, a parser as type). Booleans become --x / --no-x."""
    names = names or tuple(f.name for f in dataclasses.fields(cls))
    defaults = defaults if defaults is not None else cls()
    added = p.get_default("config_fields") or {}
    p.set_defaults(config_fields={**added, _qualified(cls): added.get(_qualified(cls), ()) + tuple(names)})
    for name in names:
        default = getattr(defaults, name)
        text = helps.get(name) or field_docs(cls).get(name) or f"{cls.__name__}.{name}"
        if default not in (None, ()):  # the comment says what None or nothing means
            text = f"{text} (default {_shown(default)})"
        text = text.replace("%", "%%")
        option, extra = (flags or {}).get(name, flag(name)), (options or {}).get(name, {})
        if isinstance(default, bool):
            p.add_argument(option, dest=name, action=argparse.BooleanOptionalAction, default=default, help=text, **extra)
        else:
            p.add_argument(option, dest=name, **{"type": _value_type(cls, name, default), "default": default,
                                                 "help": text, **extra})


def _shown(default) -> str:
    """A default as its flag takes it: a tuple of ints as HxW, of names comma-separated."""
    if isinstance(default, tuple):
        return ("x" if all(isinstance(v, int) for v in default) else ",").join(map(str, default))
    return str(default)


def _qualified(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def config_from_args(cls: type, args: argparse.Namespace, **extra):
    """`cls` built from the fields `add_fields` made flags for on this command, with `extra`
    keywords over them (the other fields keep their defaults)."""
    names = (getattr(args, "config_fields", None) or {}).get(_qualified(cls), ())
    return cls(**{**{name: getattr(args, name) for name in names}, **extra})


# -- library errors in flag names ----------------------------------------------------------------

# A config field (`EvalPlan.agents`) or a function's argument (`view_episode.out`).
_QUALIFIED = re.compile(r"\b(?:[A-Z][A-Za-z]*|[a-z]+(?:_[a-z]+)+)\.([a-z][a-z0-9_]*)\b")


def parser_flags(p: argparse.ArgumentParser) -> dict[str, str]:
    """dest -> the first long option string of every optional argument of `p`."""
    return {a.dest: next((s for s in a.option_strings if s.startswith("--")), a.option_strings[0])
            for a in p._actions if a.option_strings and a.dest != "help"}


def as_flags(message: str, flags: dict[str, str]) -> str:
    """`message` with every `Config.field` whose field a flag sets (`flags`: field -> flag)
    written as that flag; other names stay as they are."""
    return _QUALIFIED.sub(lambda m: flags.get(m.group(1), m.group(0)), message)


def translate_errors(p: argparse.ArgumentParser, **fields: str) -> None:
    """The fields (field -> flag) of this command's errors that no flag's dest names; `main`
    rewrites those and every field named as a flag's dest (`leaf_flags`) into its flags."""
    p.set_defaults(field_flags=fields)


def leaf_flags(parser: argparse.ArgumentParser) -> None:
    """Give every command parser under `parser` its complete field -> flag map (`as_flags`)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        parser.set_defaults(field_flags={**parser_flags(parser), **(parser.get_default("field_flags") or {})})
    for action in subs:
        for child in dict.fromkeys(action.choices.values()):
            leaf_flags(child)


# -- flags several commands share ----------------------------------------------------------------


def resolution_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--resolution", type=parse_resolution, default=None, metavar="HxW",
                   help=f"panorama HxW {what} (default: the paper's 112x448, envs.config.SensorConfig)")


def materials_arg(p: argparse.ArgumentParser, what: str) -> None:
    from conav_jax.envs.config import MATERIALS

    p.add_argument("--materials", choices=MATERIALS, default=None,
                   help=f"surfaces: per-instance materials with shading, or one flat colour per category {what} "
                        "(envs.config.SensorConfig.materials)")


def devices_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="devices each batch is split over (default: all visible, every host's in a multi-host run)")


def mesh(args: argparse.Namespace):
    from conav_jax.parallel import make_mesh

    return make_mesh(args.devices)


def tiny_dataset() -> tempfile.TemporaryDirectory:
    """The tiny preset in a temporary directory (benchmarks run without --data)."""
    from conav_jax.data.episodes import generate_dataset
    from conav_jax.data.presets import preset

    tmp = tempfile.TemporaryDirectory()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        generate_dataset(preset("tiny"), tmp.name)
    return tmp


def train_args(p: argparse.ArgumentParser, defaults) -> None:
    """--data, --out, the TrainConfig fields (with this command's defaults), --no-progress, --devices."""
    from conav_jax.train.loop import TrainConfig

    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--out", required=True, help="run dir: log.jsonl and checkpoints (resumed if present)")
    add_fields(p, TrainConfig, defaults=defaults)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    devices_arg(p)


def train_config(args: argparse.Namespace):
    from conav_jax.train.loop import TrainConfig

    return config_from_args(TrainConfig, args)


# -- the learned agents' runs (eval, view, bench eval) -------------------------------------------

LEARNED_AGENTS_HELP = "conav, ppo, objectgoal-oracle, objectgoal-predicted, imagegoal"


def agent_run_args(p: argparse.ArgumentParser, several: bool = False) -> None:
    """--checkpoint and the intention predictor flags of the agents that load trained runs."""
    if several:
        p.add_argument("--checkpoint", default=None, metavar="RUN | AGENT=RUN,...",
                       help=f"run dir of the learned agents ({LEARNED_AGENTS_HELP}); for several learned agents of "
                       "different runs, AGENT=RUN per agent, comma-separated (e.g. conav=runs/dagger,"
                       "objectgoal-oracle=runs/objectnav,objectgoal-predicted=runs/objectnav,imagegoal=runs/imagenav); "
                       "an entry without AGENT= is the run of the learned agents not named")
    else:
        p.add_argument("--checkpoint", default=None, help=f"run dir of the learned agent ({LEARNED_AGENTS_HELP})")
    p.add_argument("--intention", default=None, metavar="RUN",
                   help="conav/ppo/objectgoal-predicted: intention predictor run (`conav train intention`; default "
                   "for conav: the one the policy run names)")
    p.add_argument("--trajectory", default=None, metavar="RUN",
                   help="conav/ppo: trajectory predictor run (`conav train trajectory`; default for conav: the "
                   "one the policy run names)")
    p.add_argument("--ground-truth-intentions", action="store_true",
                   help="conav/ppo: feed the env's ground-truth intentions instead of predictions (privileged "
                   "upper bound, labelled so in every output)")
    p.add_argument("--pretrained", action="store_true",
                   help="conav: the policy and any predictor it reads, shipped with the package (trained on the "
                   "paper preset; conav_jax/pretrained/PROVENANCE.json) in place of --checkpoint/"
                   "--intention/--trajectory")


def use_pretrained(args: argparse.Namespace, agents: tuple[str, ...]) -> None:
    """--pretrained: the conav agent's run and the predictors it reads become the shipped ones
    (ValueError when conav is not run, or --checkpoint / --intention / --trajectory would also
    name them)."""
    if not args.pretrained:
        return
    from conav_jax.envs.agents.registry import AGENTS
    from conav_jax.pretrained import pretrained_runs

    if "conav" not in agents:
        raise ValueError("--pretrained is the conav agent's: add conav to --agent")
    if args.intention is not None or args.trajectory is not None or args.ground_truth_intentions:
        raise ValueError("--pretrained brings its own predictors: drop --intention / --trajectory / "
                         "--ground-truth-intentions")
    runs = pretrained_runs()
    given = parse_checkpoints(args.checkpoint)
    others = [a for a in agents if a != "conav" and a in AGENTS and AGENTS[a].needs_checkpoint]
    if isinstance(given, dict) and "conav" in given or isinstance(given, str) and not others:
        raise ValueError("--pretrained is the conav agent's run: drop its --checkpoint")
    if isinstance(given, str):  # a bare RUN stays the other learned agents'
        given = {None: given}
    checkpoint = {**(given or {}), "conav": str(runs["policy"])}
    args.checkpoint = (str(runs["policy"]) if len(checkpoint) == 1
                       else ",".join(f"{k}={v}" if k else v for k, v in checkpoint.items()))
    args.intention = str(runs["intention"]) if "intention" in runs else None
    args.trajectory = str(runs["trajectory"]) if "trajectory" in runs else None


def intention_kwargs(args: argparse.Namespace) -> dict:
    """envs.agents.registry.make_agent's intention keywords from `agent_run_args`' flags."""
    out = {}
    for key, run in (("intention_run", args.intention), ("trajectory_run", args.trajectory)):
        if run is not None:
            if not Path(run).is_dir():
                raise ValueError(f"--{key.removesuffix('_run')} run directory not found: {run}")
            out[key] = run
    if args.ground_truth_intentions:
        if out:
            raise ValueError("--ground-truth-intentions excludes --intention / --trajectory")
        out["ground_truth"] = True
    return out


# The names library errors give the intention keywords, as the flags that set them.
INTENTION_FLAGS = {"intention_run": "--intention", "trajectory_run": "--trajectory",
                   "ground_truth": "--ground-truth-intentions", "intention_kwargs": "--intention / --trajectory / "
                   "--ground-truth-intentions"}
