"""Design from scratch: candidate poses x lenses judged once (`candidates`), scored (`score`),
greedy selection with exchanges under the pairwise rules (`select`, `feasibility`), the time and
memory estimated up front (`budget`) and a certified bound (`bound`), then continuous refinement
by `vdo.optimize`; the speckle pattern's design (`pattern`)."""
