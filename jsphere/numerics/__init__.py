"""Numerics that know nothing of the robot: the package's one Levenberg-Marquardt
(`jsphere.numerics.lm`) and its linear solves, and sine and cosine in elementwise arithmetic
(`jsphere.numerics.trig`)."""
