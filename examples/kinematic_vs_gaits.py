"""The paper's Fig. 2 experiment: the kinematic control (2.9) driven through the dynamic model
(wheels stopped at t = 4 s) against gait control; RMS of gamma_3 after the stop."""

import jax.numpy as jnp
import numpy as np

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

p = jsphere.RobotParams.paper()
ts = jnp.linspace(0.0, 8.0, 801)
speed = float(p.R0) * 0.864  # the paper's Omega_1, (5.5)
kin = jsphere.simulate(
    p, jsphere.State.at_rest(p), jsphere.kinematic_control(p, jsphere.straight_line(speed), t_stop=4.0), 8.0, ts=ts
)
gaits = jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()])
after = np.asarray(ts) >= 4.0
print(
    f"kinematic control: sigma(gamma_3, t > 4 s) = {np.std(np.asarray(kin.gamma[:, 2])[after]):.4f}  (experiment: 0.018)"
)
print(f"gait control:      gamma_3 at the stop     = {float(gaits.gamma[-1, 2]):.12f}  (experiment sigma: 0.001)")
print(f"kinematic run at t = 4 s: x = {1e3 * float(kin.x[400]):.1f} mm (planned {1e3 * 4 * speed:.1f} mm)")
