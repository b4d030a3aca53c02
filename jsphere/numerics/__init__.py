"""Numerics that know nothing of the robot: the package's one Levenberg-Marquardt
(`jsphere.numerics.lm`) and its linear solves, IPOPT for sparse constrained problems
(`jsphere.numerics.ipopt`), and sine and cosine in elementwise arithmetic
(`jsphere.numerics.trig`)."""
