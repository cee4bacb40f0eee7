"""The simulated lab's scene: ambient background light, counted with the signal."""
import dataclasses

import numpy as np
import pytest

from drivers.sim.scene import VirtualScene


def test_background_is_light_scaled_and_counted_like_the_signal():
    base = VirtualScene.default(n_lines=2, n_x=16, n_t=64, seed=0)
    lit = dataclasses.replace(base, background=0.05)
    for exposure, gain in ((None, None), (0.02, 40)):
        diff = lit.expected_counts(0, exposure_s=exposure, gain=gain) - base.expected_counts(0, exposure_s=exposure,
                                                                                             gain=gain)
        np.testing.assert_allclose(diff, 0.05 * base.signal_scale(exposure, gain), rtol=1e-12)
    # Photon counting (no dark level, no read noise): Poisson counts of the lit mean.
    rng = np.random.default_rng(3)
    frames = np.stack([lit.render_frame(0, rng, dark=False).astype(float) for _ in range(50)])
    mean = lit.expected_counts(0) - lit.dark_level
    z = (frames.mean(axis=0) - mean).sum() / np.sqrt(mean.sum() / 50)
    assert abs(z) < 4
    # The default adds nothing.
    np.testing.assert_array_equal(dataclasses.replace(base, background=0.0).clean_line(1), base.clean_line(1))


def test_negative_background_is_refused():
    base = VirtualScene.default(n_lines=1, n_x=4, n_t=32)
    with pytest.raises(ValueError, match="background"):
        dataclasses.replace(base, background=-0.1)
