"""Measurements behind shipped settings, kept so each can be re-run to re-decide it
(`python -m bench.experiments.<name>`): the gate offsets, the energy tolerance, the other
post-training settings and their seed spread, the flicker settings, the neighbour-pooling rule,
the exposure range, and `renderloop denoise` on Mitsuba's EXRs. Not part of `renderloop bench`;
each decision and its figures are in docs/decisions.md. Built on public seams only: the loop's
`RenderLoop(spec, networks).run()`, the denoiser's `prepare`/`apply` and its config."""
