"""Float64 pure-torch twins of every Warp kernel: the tests' references, and the float64 path of
the public ops (``composite`` and ``HashGridEncoding`` given float64 inputs), which autograd
differentiates to any order."""
