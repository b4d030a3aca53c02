"""Motion planning: gait optimisation to a target, routes, plans over many robots."""
