"""The batch engine: what a vmapped solve becomes. `layout` (the named layouts and batch-size
thresholds), `dispatch` (the batching rule that picks a layout, and its custom VJP), `segment`
(one segment's solve with shared steps), `components` (the fields on scalar components),
`method` (a Runge-Kutta method on a batch), `loop` (the batch's step loop) and `adjoint` (its
discrete adjoint)."""
