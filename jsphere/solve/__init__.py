"""Integration of the equations of motion with diffrax: `simulate`, its options and named
results, the `Trajectory` and its diagnostics; `solve.batched` is the engine for many trials."""
