"""Fitting the encoder to TouchSim reference spike trains (paper section 2.4): the objective of
eqs. 1-10 (:mod:`.objective`), the normalised search space (:mod:`.space`), the fit's plan
(:mod:`.plan`) resolved from the build's profile (:mod:`.profile`) by the policy (:mod:`.policy`),
and the parallel CMA-ES driver behind ``touchreal fit`` (:mod:`.fit`). See docs/fitting.md."""
