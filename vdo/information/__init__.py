"""The machinery under `vdo.objective`: the mean-field DIC information of a camera layout, worked
out pair by pair. `vdo.objective` is the public face (the model in its docstring; `information`,
`fields`, `sample_fields`, `score`, `score_and_grad`, and the names below re-exported); the
modules here, bottom to top:

inputs      what it is computed from: `CameraParams`, `Samples`, `Settings`, `KAPPA_BOX`
projection  per (camera, sample) pair: projection, sensitivity s (pixel/m), footprint A
            (pixel/m), soft weight w; the camera and sample tables
tensor      footprint -> gradient tensor T (1/pixel^2) by the floored-gap spectral formula; the
            speckle's gradient energy G (`TableEnergy`, `GaussianFieldEnergy`)
views       the sparse pair list (`ViewData`): which pairs, laid out camera-major in blocks
blocks      the per-pair block Omega w |det A| C_i (1/m^2), its per-sample sums over chunks,
            and the hand-written reverse pass

Floor 6 (docs/architecture.md): it imports `vdo.model` and `vdo.core` only, and `vdo.objective`
(floor 7) stands on it."""
