"""The converted shell centre's height (`jsphere.capture.centre`): its median and variation,
noise left out, and the warnings that compare them with the shell radius."""

import warnings

import numpy as np
import pytest

from jsphere.capture.centre import CENTRE_HEIGHT_SPREAD, CENTRE_HEIGHT_TOL, centre_height, check_centre_height
from jsphere.capture.trial import Trial
from jsphere.capture.validation import CaptureWarning


def _trial(z):
    t = np.arange(len(z)) * 0.01
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    return Trial(t, 0.3 * t, 0.05 * np.sin(t), q, np.zeros((len(t), 3)), "wheel_speeds", z)


def _check(trial, R0=0.15):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CaptureWarning)
        msgs = check_centre_height(trial, R0, source="take.csv", fix="FIX", floor="FLOOR")
    assert [str(w.message) for w in caught] == msgs
    return msgs


def test_noise_is_not_variation():
    rng = np.random.default_rng(0)
    z = 0.15 + rng.normal(0.0, 1e-3, 300)
    z[[10, 11, 12]] = np.nan  # gaps are left out
    h = centre_height(_trial(z))
    assert abs(h.median - 0.15) < 3e-4 and h.spread < 1.5e-3 and h.frames == 297
    assert _check(_trial(z)) == []


def test_a_height_off_the_radius_is_named_with_the_fix():
    z = np.full(300, 0.15 + 2 * CENTRE_HEIGHT_TOL)
    (msg,) = _check(_trial(z))
    assert "0.1560 m above the floor (median over 300 frames; FLOOR), 6.0 mm above" in msg and msg.endswith(": FIX.")
    (msg,) = _check(_trial(np.full(300, 0.15 - 2 * CENTRE_HEIGHT_TOL)))
    assert "6.0 mm below" in msg
    assert _check(_trial(np.full(300, 0.15 + 0.5 * CENTRE_HEIGHT_TOL))) == []


def test_a_height_that_rises_and_falls_is_named_whatever_the_floor():
    t = np.arange(300) * 0.01
    z = 0.25 + 0.8 * CENTRE_HEIGHT_SPREAD * np.sin(2 * np.pi * t)  # a floor 10 cm below height 0
    msgs = _check(_trial(z))
    assert len(msgs) == 2 and "varies by 7.6 mm" in msgs[1] and "the floor is not level, or FIX" in msgs[1], msgs
    assert centre_height(_trial(z)).spread == pytest.approx(1.6 * CENTRE_HEIGHT_SPREAD * np.sin(0.45 * np.pi), rel=0.05)


def test_a_wrong_up_axis_is_left_to_its_own_warning():
    t = np.arange(300) * 0.01
    assert _check(_trial(0.05 + 0.3 * t)) == []  # z follows the motion: the "height" finding says it
