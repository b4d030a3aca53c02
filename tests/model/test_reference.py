"""jsphere against the independent Kane-method derivation in ../shared/reference."""

import numpy as np
import pytest

import jsphere


def test_accelerations_match_reference(reference, ref_params):
    for case in reference["accel_cases"]:
        p = (
            ref_params[case["params"]]
            if isinstance(case["params"], str)
            else jsphere.RobotParams.from_dict(case["params"])
        )
        wd, Wd = jsphere.accelerations(p, case["gamma"], case["omega"], case["Omega"], case["K"])
        got = np.concatenate([wd, Wd])
        ref = np.concatenate([case["omega_dot"], case["Omega_dot"]])
        err = np.linalg.norm(got - ref)
        assert err <= 1e-9 * np.linalg.norm(ref) + 1e-10, (case["label"], err)
        chi_dot = jsphere.wheel_speeds(p, case["omega"], case["Omega"])
        np.testing.assert_allclose(chi_dot, case["chi_dot"], atol=1e-10, err_msg=case["label"])
        v = jsphere.rolling_velocity(p, np.asarray(case["gamma"]), np.asarray(case["Omega"]))
        R = np.stack([case["alpha"], case["beta"], case["gamma"]])
        np.testing.assert_allclose(v, case["v_platform"], atol=1e-12)
        np.testing.assert_allclose((R @ v)[:2], case["xdot_ydot"], atol=1e-12)


def _index(traj, t, side):
    idx = np.nonzero(np.abs(np.asarray(traj.ts) - t) < 1e-12)[0]
    return idx[0] if side == "left" else idx[-1]


CHAINS = {
    # name in the reference -> (gaits, reset, index of the gait the samples belong to)
    "acceleration": (lambda: [jsphere.acceleration()], False, 0),
    "braking_continuation": (lambda: [jsphere.acceleration(), jsphere.braking()], False, 1),
    "turn_reset": (lambda: [jsphere.acceleration(), jsphere.turn()], True, 1),
}


@pytest.mark.parametrize("pset", ["P1_fit", "P0_j0"])
@pytest.mark.parametrize("chain", list(CHAINS))
def test_gait_time_series(reference, ref_params, pset, chain):
    p = ref_params[pset]
    make, reset, k = CHAINS[chain]
    tr = jsphere.simulate_gaits(p, make(), reset=reset)
    for s in reference["gaits"][pset][chain]["samples"]:
        t = 2.0 * k + s["t"]
        # within a gait: its own samples (the left limit at its end, the right limit at its start)
        i = _index(tr, t, "right" if s["t"] == 0.0 else "left")
        assert int(tr.segment[i]) == k
        for f, tol in (
            ("Omega", 1e-8),
            ("K", 1e-8),
            ("chi_dot", 1e-8),
            ("gamma", 1e-8),
            ("omega", 1e-8),
            ("alpha", 1e-8),
            ("beta", 1e-8),
        ):
            np.testing.assert_allclose(getattr(tr, f)[i], s[f], atol=tol, err_msg=f"{chain} {f} t={s['t']}")
        np.testing.assert_allclose([tr.x[i], tr.y[i]], [s["x"], s["y"]], atol=1e-6, err_msg=f"{chain} x,y t={s['t']}")


def _end(tr, k):
    return int(np.nonzero(np.asarray(tr.segment) == k)[0][-1])


@pytest.mark.parametrize("pset", ["P1_fit", "P0_j0"])
def test_gait_summaries(reference, ref_params, pset):
    p = ref_params[pset]
    S = reference["gaits"][pset]["summary"]
    acc, brk, trn = jsphere.acceleration(), jsphere.braking(), jsphere.turn()
    brk45 = jsphere.braking(phi=np.pi / 4)

    tr = jsphere.simulate_gaits(p, [acc, brk])
    np.testing.assert_allclose(tr.Omega[_end(tr, 0)], S["acceleration"]["Omega_end"], atol=1e-8)
    np.testing.assert_allclose(
        1e3 * np.array([tr.x[-1], tr.y[-1]]), S["straight_continuation"]["stop_xy_mm"], atol=1e-3
    )
    np.testing.assert_allclose(tr.Omega[-1], S["straight_continuation"]["Omega_end"], atol=1e-8)

    tr = jsphere.simulate_gaits(p, [acc, brk], reset=True)
    np.testing.assert_allclose(1e3 * np.array([tr.x[-1], tr.y[-1]]), S["straight_reset"]["stop_xy_mm"], atol=1e-3)
    np.testing.assert_allclose(tr.Omega[-1], S["straight_reset"]["Omega_end"], atol=1e-8)

    for name, reset in (("turn_reset", [True, None]), ("turn_continuation", False)):
        tr = jsphere.simulate_gaits(p, [acc, trn, brk45], reset=reset)
        T = S[name]
        i = _end(tr, 1)
        np.testing.assert_allclose(tr.Omega[i], T["Omega_after_turn"], atol=1e-8)
        np.testing.assert_allclose(1e3 * np.array([tr.x[i], tr.y[i]]), T["xy_end_turn_mm"], atol=1e-3)
        np.testing.assert_allclose(tr.Omega[-1], T["Omega_after_brake"], atol=1e-8)
        np.testing.assert_allclose(1e3 * np.array([tr.x[-1], tr.y[-1]]), T["xy_end_brake_mm"], atol=1e-3)
        seg = np.asarray(tr.segment)
        np.testing.assert_allclose(np.abs(tr.K[seg == 1]).max(0), T["turn_K_peak_abs"], rtol=1e-3)

    for name, Om in (("brake_signfixed_5.7", (-0.868, 0.852, 0.0)), ("brake_printed_5.7", (0.868, 0.852, 0.0))):
        tr = jsphere.simulate_gaits(p, [acc, trn, brk45], reset=[True, Om])
        np.testing.assert_allclose(tr.Omega[-1], S[name]["Omega_after_brake"], atol=1e-8)
        np.testing.assert_allclose(1e3 * np.array([tr.x[-1], tr.y[-1]]), S[name]["xy_end_brake_mm"], atol=1e-3)

    F = S["turn_full_stop_brake"]
    tr = jsphere.simulate_gaits(p, [acc, trn, jsphere.braking(theta_max=F["theta_max"], phi=F["phi"])])
    np.testing.assert_allclose(tr.Omega[-1], F["Omega_end"], atol=1e-8)
    np.testing.assert_allclose(1e3 * np.array([tr.x[-1], tr.y[-1]]), F["stop_xy_mm"], atol=1e-3)
