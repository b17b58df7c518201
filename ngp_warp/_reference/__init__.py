"""Float64 pure-torch twins of every Warp kernel, used only by tests and benchmarks."""
