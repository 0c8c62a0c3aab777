"""The reference documents stay references: the README and BENCHMARKS.md within their sizes
(dated measurements and their story live in results/*/README.md), every local link resolving,
the README's results tables copied from the tables.md files they link."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMITS_BYTES = {"README.md": 15_000, "BENCHMARKS.md": 25_000}


def test_reference_documents_stay_within_their_sizes():
    sizes = {name: len((ROOT / name).read_bytes()) for name in LIMITS_BYTES}
    assert all(sizes[n] <= LIMITS_BYTES[n] for n in LIMITS_BYTES), sizes


def test_local_links_of_the_reference_documents_resolve():
    missing = []
    for name in LIMITS_BYTES:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", (ROOT / name).read_text()):
            if not re.match(r"[a-z]+://", target) and not (ROOT / target).exists():
                missing.append((name, target))
    assert not missing, missing


def _results_tables(readme: str) -> list[tuple[str, list[list[str]]]]:
    """(the tables.md the paragraph before it links, the rows' cells) of each table in the
    README's Results section."""
    section = readme.split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    found = []
    for block in re.split(r"\n\s*\n", section):
        lines = [line for line in block.splitlines() if line.startswith("|")]
        linked = re.findall(r"\[tables\]\(([^)]+tables\.md)\)", block)
        if linked:
            found.append([linked[0], []])
        if lines and found:
            found[-1][1] += [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    return [(link, rows) for link, rows in found if rows]


def test_the_readmes_results_are_those_of_the_tables_they_link():
    # Every figure of a README results table appears, as written, in the tables.md its paragraph
    # links (rendered by `conav reproduce --stage tables`): the README copies, it does not compute.
    tables = _results_tables((ROOT / "README.md").read_text())
    assert len(tables) >= 2, "the README's Results section lost its tables or their [tables](...) links"
    missing = []
    for link, rows in tables:
        rendered = (ROOT / link).read_text()
        for row in rows:
            for cell in row[1:]:
                for part in cell.split(" / "):
                    if re.fullmatch(r"[-+−]?\d[\d.,]*( ± [\d.]+)?", part) and part not in rendered:
                        missing.append((link, row[0], part))
    assert not missing, missing
