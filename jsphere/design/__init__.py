"""Optimal excitation for identification: input programmes that make the free parameters of a
fit as well determined as possible (`design_excitation`, `jsphere design`)."""
