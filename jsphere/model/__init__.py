"""The physics: parameters, named parameter values, the state and its flat layout, rotations,
the kinematics (rolling, constraints, wheel speeds) and the dynamics (3.4), as pure JAX."""
