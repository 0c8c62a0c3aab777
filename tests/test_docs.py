"""The reference documents stay references: the README and BENCHMARKS.md within their sizes
(dated measurements and their story live in results/*/README.md), every local link resolving."""

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
