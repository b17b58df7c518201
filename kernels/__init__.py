"""Warp kernels of ngp-warp (no torch imports here): one module per concern, each forward
beside its hand-written backward. Installed as ``ngp_warp.kernels``."""
