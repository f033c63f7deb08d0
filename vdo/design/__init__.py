"""Design from scratch: candidate poses x lenses judged once, greedy selection with exchanges under
the pairwise rules, then continuous refinement by `vdo.optimize`."""
