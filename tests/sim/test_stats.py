"""Wilson score intervals: edge cases, known values, coverage ordering."""

import math

import pytest

from sim.stats import proportion, wilson_interval


def test_no_trials_gives_the_uninformative_interval():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    p = proportion(0, 0)
    assert math.isnan(p.rate) and (p.lo, p.hi) == (0.0, 1.0)
    assert "0 trials" in str(p)


def test_zero_successes_has_lower_bound_exactly_zero_and_positive_upper_bound():
    lo, hi = wilson_interval(0, 20)
    z = 1.959963984540054
    assert lo == 0.0
    assert hi == pytest.approx(z * z / (20 + z * z))  # closed form of the k = 0 upper bound


def test_all_successes_has_upper_bound_exactly_one_and_mirrors_zero_successes():
    lo, hi = wilson_interval(20, 20)
    assert hi == 1.0
    assert lo == pytest.approx(1.0 - wilson_interval(0, 20)[1])


def test_matches_the_textbook_value_for_half_of_ten():
    # Wilson interval for 5/10 at 95%: centre 0.5, half-width z*sqrt(0.025 + z^2/400)/(1 + z^2/10).
    z = 1.959963984540054
    half = z * math.sqrt(0.25 / 10 + z * z / 400) / (1 + z * z / 10)
    lo, hi = wilson_interval(5, 10)
    assert (lo, hi) == pytest.approx((0.5 - half, 0.5 + half))
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)


def test_interval_contains_the_rate_and_shrinks_with_more_trials():
    for k, n in [(1, 3), (9, 10), (180, 200), (450, 500)]:
        lo, hi = wilson_interval(k, n)
        assert 0.0 <= lo <= k / n <= hi <= 1.0
    assert (
        wilson_interval(900, 1000)[1] - wilson_interval(900, 1000)[0]
        < wilson_interval(90, 100)[1] - wilson_interval(90, 100)[0]
    )


def test_higher_confidence_gives_a_wider_interval():
    lo95, hi95 = wilson_interval(30, 50, 0.95)
    lo99, hi99 = wilson_interval(30, 50, 0.99)
    assert lo99 < lo95 and hi99 > hi95


@pytest.mark.parametrize("k,n", [(-1, 5), (6, 5), (0, -1), (1.5, 3), (True, 3)])
def test_invalid_counts_are_rejected(k, n):
    with pytest.raises(ValueError):
        wilson_interval(k, n)


def test_invalid_confidence_is_rejected():
    with pytest.raises(ValueError, match="confidence"):
        wilson_interval(1, 2, confidence=1.0)


def test_proportion_formats_percent_and_serialises():
    p = proportion(180, 200)
    assert str(p).startswith("90.0% (180/200; 95% CI [")
    assert p.to_dict()["k"] == 180 and p.to_dict()["n"] == 200
