"""Training: settings and their per-scene defaults (``config``, ``scene_defaults``), the model
and its optimizer state, one step and the trainer, checkpoints and run folders, appearance and
camera refinement, data-parallel training, the memory estimate and the built-in demos. Imports
the ops and data, never outputs or the CLI."""
