"""The differentiable ops' torch layer: each module wraps its Warp kernels (``ngp_warp.kernels``,
same file names) in an autograd Function and a public function that checks its inputs, with a
float64 twin of the same name in ``ngp_warp._reference``. Also the field they drive
(``field``), the training batch's rays (``batch``), CUDA-graph capture (``graphs``) and nerfacc's
volume-rendering helpers. Imports only the Warp glue (``ngp_warp._wp``), kernels and twins."""
