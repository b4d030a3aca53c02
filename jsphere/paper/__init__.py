"""The paper's Section 5 recomputed: the reproduction behind `jsphere reproduce`."""
