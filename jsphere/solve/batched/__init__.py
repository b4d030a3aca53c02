"""The batch engine: what a vmapped solve becomes. Dispatch (the batching rule), the scalar-
component fields, the shared-step Runge-Kutta loop and its discrete adjoint, per-trial steps."""
