"""Ten lines: the paper's straight-line gaits, their torques replayed through the dynamics,
and a gradient of the stop point with respect to the tilt amplitude."""

import jax
import jax.numpy as jnp

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

p = jsphere.RobotParams.paper()
tr = jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()])
print(f"stop point: x = {1e3 * tr.x[-1]:.3f} mm, y = {1e3 * tr.y[-1]:.3f} mm")

sim = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques.from_samples(tr.ts, tr.K), 4.0, ts=tr.ts)
print(f"torque replay differs by {1e3 * float(jnp.max(jnp.abs(sim.x - tr.x))):.2e} mm")


def stop(theta_max):
    gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
    return jsphere.simulate_gaits(p, gaits, ts=jnp.array([4.0])).x[-1]


print(f"d(stop)/d(theta_max) = {jax.grad(stop)(0.1):.4f} m/rad")
