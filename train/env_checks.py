"""What a trainer asks of the envs it is given, checked before it renders or writes anything.

A trainer takes its train env (and a validation env where it validates) built by its caller
(`*_from_data` builds them from a dataset directory); these checks say, in the terms of the
config fields that ask for it, which split, panorama or episode end an env lacks. Each takes
the env's EpisodeSplit or, for the sensor and the episode end, the ConavEnv itself.
"""

from __future__ import annotations

from conav_jax.data.episodes import EpisodeSplit


def check_split(split: EpisodeSplit, name: str, role: str, field: str | None = None) -> None:
    """ValueError unless `split`, of the trainer's argument `role`, is the split `name` (`field`:
    the config field that names it, if one does)."""
    if split.name != name:
        named = f" ({field})" if field else ""
        raise ValueError(f"{role} holds the {split.name!r} split; expected {name!r}{named}")


def check_same_data(train: EpisodeSplit, val: EpisodeSplit) -> None:
    """ValueError unless both splits come from one dataset (the same content hash; splits made
    by hand have none): a run records a single dataset."""
    if train.content_hash != val.content_hash:
        raise ValueError(f"train_env and val_env come from different datasets (content hashes {train.content_hash} "
                         f"and {val.content_hash})")


def check_sensor(env, role: str, resolution, field: str, materials: str | None = None,
                 materials_field: str | None = None) -> None:
    """ValueError unless `env` renders panoramas of `resolution` (H, W), the value of the config
    field `field`, and, where given, `materials` (the value of `materials_field`)."""
    sensor = env.config.sensor
    h, w = resolution
    if tuple(sensor.resolution) != (h, w):
        raise ValueError(f"{field} is ({h}, {w}) but {role} renders {tuple(sensor.resolution)} panoramas; build it "
                         f"with SensorConfig(resolution=({h}, {w}))")
    if materials is not None and sensor.materials != materials:
        raise ValueError(f"{materials_field} is {materials!r} but {role} renders {sensor.materials!r}; build it with "
                         f"SensorConfig(materials={materials!r})")


def check_ends_at_reach(env, role: str, why: str) -> None:
    """ValueError unless `env`'s episodes end at the robot's first reach of the goal (`why`: the
    trainer's reason)."""
    if not env.config.end_at_reach:
        raise ValueError(f"{role} must end its episodes at the first reach ({why}): build it with "
                         "EnvConfig(end_at_reach=True)")
