"""From a raw capture to a trainable scene: read the inputs, EDI latents, COLMAP poses, layout.

Modules, in the order the data flows through them:

- :mod:`edygs_ns.preprocess.inputs`: every input form (AEDAT4, exposure table + event file,
  E2NeRF folder) turned into one neutral :class:`~edygs_ns.preprocess.inputs.Capture`.
- :mod:`edygs_ns.preprocess.colmap`: pycolmap on the latent frames (SIFT, sequential matching,
  incremental mapping) and the registration report.
- :mod:`edygs_ns.preprocess.writer`: the processed layout of docs/layouts.md.
- :mod:`edygs_ns.preprocess.steps`: the resumable step runner (timing, reuse, --overwrite).
- :mod:`edygs_ns.preprocess.pipeline`: the steps strung together over one config (``process``).

The command line is :mod:`edygs_ns.scripts.process` (``edygs-process``).
"""
