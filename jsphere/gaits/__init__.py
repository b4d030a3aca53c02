"""Gait control (Section 4): gaits, their families, and `simulate_gaits`."""
