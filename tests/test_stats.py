"""eval.stats on hand-computed numbers: seed-level t-intervals and paired contrasts."""

import math

import pytest

from conav_jax.eval.stats import paired_difference, resolved, seed_summary

T_975 = {2: 4.302652729749462, 7: 2.364624251592785}  # t quantiles for 2 and 7 degrees of freedom


def test_seed_summary_is_the_t_interval_over_seeds():
    s = seed_summary([10.0, 12.0, 17.0])
    sd = math.sqrt(((10 - 13) ** 2 + (12 - 13) ** 2 + (17 - 13) ** 2) / 2)
    assert (s.n, s.mean) == (3, 13.0) and s.sd == pytest.approx(sd)
    half = T_975[2] * sd / math.sqrt(3)
    assert (s.lo, s.hi) == (pytest.approx(13 - half), pytest.approx(13 + half))
    assert s.text() == f"13.0 ± {sd:.1f} [{13 - half:.1f}, {13 + half:.1f}] (n=3)"


def test_one_seed_has_no_interval_and_resolves_nothing():
    s = seed_summary([4.0])
    assert (s.lo, s.hi, s.sd) == (4.0, 4.0, 0.0) and s.text() == "4.0 (1 seed)" and not resolved(s)


def test_paired_difference_pairs_by_seed_not_by_position():
    row = {0: 20.0, 1: 25.0, 2: 18.0, 3: 30.0, 4: 22.0, 5: 19.0, 6: 24.0, 7: 21.0, 9: 99.0}
    ref = {7: 20.0, 6: 21.0, 5: 17.0, 4: 18.0, 3: 27.0, 2: 15.0, 1: 22.0, 0: 16.0}
    d = paired_difference(row, ref)
    diffs = [4.0, 3.0, 3.0, 3.0, 4.0, 2.0, 3.0, 1.0]  # seeds 0..7; seed 9 has no reference
    mean = sum(diffs) / 8
    sd = math.sqrt(sum((x - mean) ** 2 for x in diffs) / 7)
    assert d.n == 8 and d.mean == pytest.approx(mean) and d.sd == pytest.approx(sd)
    assert d.lo == pytest.approx(mean - T_975[7] * sd / math.sqrt(8))
    assert resolved(d)
    assert not resolved(paired_difference({0: 1.0, 1: -1.0}, {0: 0.0, 1: 0.0}))


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="no seed in common"):
        paired_difference({0: 1.0}, {1: 1.0})
    with pytest.raises(ValueError, match="finite"):
        seed_summary([1.0, float("nan")])
    with pytest.raises(ValueError, match="1-D"):
        seed_summary([])
