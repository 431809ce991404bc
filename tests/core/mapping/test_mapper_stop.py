"""The map-only stage's convergence test after a loop correction (``Mapper.optimise(stop_gain=...)``)."""

from neb_slam_core.mapping.mapper import STOP_WINDOW, _flattened


def _losses(window_means: list[float]) -> list[float]:
    """Per-step losses whose windows of STOP_WINDOW steps have these means (alternating +-0.01 inside)."""
    return [m + (0.01 if i % 2 else -0.01) for m in window_means for i in range(STOP_WINDOW)]


def test_stops_at_the_first_window_that_gains_less_than_the_share():
    means = [1.0, 0.9, 0.85, 0.845, 0.80]  # gains 10 %, 5.6 %, 0.6 %, 5.3 %
    losses = _losses(means)
    stops = [n for n in range(1, len(losses) + 1) if _flattened(losses[:n], min_iterations=50, stop_gain=0.01)]
    assert stops[0] == 4 * STOP_WINDOW  # the 0.85 -> 0.845 window: 0.59 % < 1 %
    assert all(n % STOP_WINDOW == 0 for n in stops)  # only at the end of a window


def test_not_before_min_iterations_nor_before_two_windows():
    flat = _losses([1.0, 1.0, 1.0, 1.0])
    assert not _flattened(flat[:STOP_WINDOW], min_iterations=0, stop_gain=0.01)  # no window to compare with
    assert _flattened(flat[:2 * STOP_WINDOW], min_iterations=0, stop_gain=0.01)
    assert not _flattened(flat[:2 * STOP_WINDOW], min_iterations=75, stop_gain=0.01)
    assert _flattened(flat[:3 * STOP_WINDOW], min_iterations=75, stop_gain=0.01)


def test_a_rising_loss_counts_as_flat_and_a_steady_fall_never_stops():
    assert _flattened(_losses([1.0, 1.05]), min_iterations=0, stop_gain=0.01)
    falling = _losses([1.0 * 0.97 ** k for k in range(8)])  # 3 % per window
    assert not any(_flattened(falling[:n], 0, 0.01) for n in range(1, len(falling) + 1))
