"""What a trained field gives: the view renderer, evaluation and its metrics, camera paths and
videos, mesh and point export (PLY), and the kernel benchmark. Imports ops, data and training."""
