"""Numerics that know nothing of the robot: the package's one Levenberg-Marquardt
(`jsphere.numerics.lm`) and its linear solves."""
