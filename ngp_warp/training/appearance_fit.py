"""An appearance code for a view that has none: fitted on the left half of its image.

A field with per-image appearance codes (:attr:`ngp_warp.ops.field.NGPField.appearance`) has no code
for a held-out view. Rendered with the mean code, a view whose exposure or white balance differs
from the average loses PSNR to a colour shift that no geometry can fix. As nerfstudio's
evaluation does, :func:`fit_appearance_code` fits that view's code on the LEFT half of its image
(columns < width // 2), the field frozen, and the view is then scored on the RIGHT half
(:func:`right_half`), which the fit never saw:

.. math::

    e^* = \\arg\\min_e \\frac{1}{|B|} \\sum_{p \\in B} \\lVert C(r_p; e) - I_p \\rVert^2
          + \\frac{\\lambda}{A} \\lVert e - e_0 \\rVert^2,
    \\qquad B \\subset \\{(x, y) : x < \\lfloor W / 2 \\rfloor\\}

with :math:`C(r; e)` the training render of ray :math:`r` with code :math:`e` for every sample,
minimised by Adam from the start code :math:`e_0` (the mean training code unless given; the
evaluation gives the nearest training camera's) on a fresh random batch :math:`B` per iteration.
The pull :math:`\\lambda` (:data:`FIT_PULL`) keeps the code near :math:`e_0` where the left half
alone would have it fit the half's content rather than the view's exposure.
The samples' weights and geometry do not depend on the code, so they are computed once for many
iterations' rays, and each iteration evaluates only the colour head (:func:`_fit_code`).
"""

from __future__ import annotations

import torch

from ngp_warp._checks import check_distances
from ngp_warp.training.camera_refinement import CameraRefinement
from ngp_warp.ops.optim import Adam
from ngp_warp.data.cameras import generate_rays
from ngp_warp.ops.field import NGPField
from ngp_warp.training.trainer import Trainer

FIT_ITERATIONS = 100
FIT_LR = 1e-2
FIT_PULL = 3e-3  # λ: on fox's held-out views (H200, 60 s, four runs), fitted from the nearest camera's
                 # code, right halves +0.21 to +0.38 dB over no pull; 1e-2 within 0.04 of it, 1e-3 within 0.08
FIT_RAYS_PER_ITERATION = {"cuda": 4096, "cpu": 256}  # by device type
FIT_GROUP_RAYS = 1 << 16  # rays whose samples are marched and kept at once
POSE_LR = 1e-3            # a view's pose correction: Adam's first learning rate ...
POSE_LR_FINAL = 1e-5      # ... decayed exponentially to this over the fit


def right_half(image: torch.Tensor) -> torch.Tensor:
    """The columns a fitted view is scored on: [H, W, C] → [H, W - W // 2, C] (columns ≥ W // 2)."""
    return image[:, image.shape[1] // 2:]


def nearest_training_code(trainer: Trainer, c2w: torch.Tensor) -> torch.Tensor:
    """[A] float32: the appearance code of the training image whose camera centre lies nearest
    to that of ``c2w`` ([3, 4] or [4, 4]): a held-out frame of a capture shares its neighbours'
    exposure and white balance far more than the mean over all images does. ValueError for a
    field without appearance codes."""
    if trainer.field.appearance is None:
        raise ValueError("nearest_training_code needs a field with appearance codes (appearance_dim > 0)")
    centres = trainer.train_split.c2w[:, :, 3]
    nearest = (centres - c2w[:3, 3].to(centres)).norm(dim=-1).argmin()
    return trainer.field.appearance.weight[nearest].detach()


def _check_fit_inputs(trainer: Trainer, c2w, intrinsics, width: int, height: int, image, distortion,
                      iterations: int, rays_per_iteration: int, pull) -> None:
    """One-line ValueErrors for a field without codes, inputs of the wrong shape and a pull that
    is not a finite number ≥ 0."""
    if trainer.field.appearance is None:
        raise ValueError("fit_appearance_code needs a field with appearance codes (appearance_dim > 0)")
    if type(width) is not int or type(height) is not int or width < 2 or height < 1:
        raise ValueError(f"width must be an int ≥ 2 and height an int ≥ 1, got {width!r} x {height!r}")
    for name, t, shape in (("c2w", c2w, (3, 4)), ("intrinsics", intrinsics, (4,)),
                           ("image", image, (height, width, 3)), ("distortion", distortion, (6,))):
        if name == "distortion" and t is None:
            continue
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or not t.is_floating_point():
            got = getattr(t, "shape", type(t).__name__)
            raise ValueError(f"{name} must be a float {list(shape)} tensor, got {got}")
    if type(iterations) is not int or iterations < 1 or type(rays_per_iteration) is not int or rays_per_iteration < 1:
        raise ValueError(f"iterations and rays_per_iteration must be ints ≥ 1, got {iterations!r}, "
                         f"{rays_per_iteration!r}")
    check_distances(pull=pull)


def _left_half_pixels(width: int, height: int, iterations: int, rays: int, seed: int) -> tuple[torch.Tensor, ...]:
    """(px, py) [iterations, R] int64 on the CPU: R = ``rays`` uniform pixels with column <
    width // 2 per iteration, drawn from a generator of their own (the global RNG is left
    alone); every left-half pixel in every iteration when there are no more than ``rays``."""
    half = width // 2
    if half * height <= rays:
        py, px = torch.meshgrid(torch.arange(height), torch.arange(half), indexing="ij")
        return px.reshape(1, -1).expand(iterations, -1), py.reshape(1, -1).expand(iterations, -1)
    gen = torch.Generator().manual_seed(seed)
    px = torch.randint(0, half, (iterations, rays), generator=gen)
    py = torch.randint(0, height, (iterations, rays), generator=gen)
    return px, py


def _field_with_code_and_positions(field: NGPField, code: torch.Tensor):
    """field_fn of :func:`ngp_warp.render_rays` that colours every sample with ``code`` ([A]
    float32, requires grad), with σ and the geometry features differentiable in the positions
    (:meth:`NGPField.forward`'s path), so that gradients reach a pose correction."""
    def field_fn(positions: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = field._geometry(positions)
        return field._sigma(h, positions), field.colour(h, directions, code, differentiable=True)

    return field_fn


def fit_appearance_and_pose(trainer: Trainer, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                            image: torch.Tensor, distortion: torch.Tensor | None = None, fisheye: bool = False,
                            background: float | None = 1.0, iterations: int = FIT_ITERATIONS,
                            rays_per_iteration: int | None = None, lr: float = FIT_LR,
                            seed: int = 0, start: torch.Tensor | None = None,
                            pull: float = FIT_PULL) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`fit_appearance_code` that also fits the view's pose: a rotation about its camera
    centre and a translation (:class:`~ngp_warp.training.camera_refinement.CameraRefinement`), Adam from
    :data:`POSE_LR` decayed to :data:`POSE_LR_FINAL`, on the same left-half pixels (``start`` and
    ``pull`` as there; the pose is not pulled). Returns the
    code [A] and the corrected c2w [3, 4] float32 (detached). For bounded fields only (a
    contracted field gives its positions no gradient): ValueError otherwise."""
    if trainer.field.contraction is not None:
        raise ValueError("fitting a view's pose needs a bounded field (no contraction)")
    pose = CameraRefinement(1, trainer.device)
    code = _fit(trainer, c2w, intrinsics, width, height, image, distortion, fisheye, background, iterations,
                rays_per_iteration, lr, seed, pose, start, pull)
    return code, pose.refined_c2w(c2w[None])[0]


def fit_appearance_code(trainer: Trainer, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int,
                        image: torch.Tensor, distortion: torch.Tensor | None = None, fisheye: bool = False,
                        background: float | None = 1.0, iterations: int = FIT_ITERATIONS,
                        rays_per_iteration: int | None = None, lr: float = FIT_LR,
                        seed: int = 0, start: torch.Tensor | None = None, pull: float = FIT_PULL) -> torch.Tensor:
    """The appearance code that best renders the left half of ``image`` near the ``start`` code
    (the math in the module docstring), the field's weights untouched.

    Each iteration renders ``rays_per_iteration`` rays through random left-half pixel centres
    (with replacement; one ray per pixel) with the trainer's training render
    (:meth:`~ngp_warp.training.model.RadianceModel.render`, unjittered samples as in
    :meth:`Trainer.render_image`, pruned by the field's density), the weight average in the
    field when it is on, over ``background``; the loss is the mean squared error, its gradient
    taken for the code alone (no ``.grad`` reaches the field).

    Defaults: Adam's step is about ``lr`` per coordinate whatever the gradient's scale, so
    ``lr`` = 1e-2 over 100 iterations lets each coordinate travel up to 1, past the trained
    codes (norms 0.2 to 1.1 after 300 steps on a 48-pixel unbounded scene whose training images
    were scaled by exposures 0.6 to 1.4), while each late step moves the colour too little to
    matter. 16 unknowns need few pixels: 256 rays per iteration (the CPU default; about 0.1 ms
    a ray there) gave the held-out PSNR of fitting on all 1152 left-half pixels to 0.03 dB on
    that scene (four test views scaled by 0.65 to 1.3: mean code 14.2 to 17.6 dB, fitted 14.9
    to 21.4 dB, 2 to 3 s a view on 2 busy cores); CUDA's 4096 (not timed here) averages the
    batch's noise further at little cost on a GPU, where an iteration is bound by its launches
    and host syncs rather than its rays.
    Images with no more left-half pixels than that take all of them in every iteration.

    Args:
        trainer: a trainer whose field has appearance codes.
        c2w: [3, 4] float32 camera-to-world. intrinsics: [4] float32 fx, fy, cx, cy.
        width, height: the image size in pixels (width ≥ 2).
        image: [height, width, 3] float32 in [0, 1], composited as the evaluation scores it
            (over ``background``), on any device.
        distortion: optional [6] float32 k1 k2 k3 k4 p1 p2; ``fisheye``: OpenCV's fisheye lens.
        background: the colour (float) behind the field, as the view is rendered; None: the
            field's learned environment.
        iterations, rays_per_iteration, lr: Adam's iterations, batch (None: by the device,
            :data:`FIT_RAYS_PER_ITERATION`) and learning rate.
        seed: the pixels' random generator (the fit is deterministic given it).
        start: [A] float32 code :math:`e_0` Adam starts from and the fit is pulled toward (e.g.
            the nearest training camera's); None: the mean of the training codes.
        pull: :math:`\\lambda \\ge 0`, the weight of the squared distance to ``start`` (0: none).

    Returns:
        [A] float32 code on the trainer's device (detached).

    Raises:
        ValueError: one line, for a field without appearance codes or inputs of the wrong shape.
    """
    return _fit(trainer, c2w, intrinsics, width, height, image, distortion, fisheye, background, iterations,
                rays_per_iteration, lr, seed, None, start, pull)


def _fit(trainer: Trainer, c2w, intrinsics, width: int, height: int, image, distortion, fisheye: bool,
         background: float | None, iterations: int, rays_per_iteration: int | None, lr: float, seed: int,
         pose: CameraRefinement | None, start: torch.Tensor | None, pull: float) -> torch.Tensor:
    """The fit of :func:`fit_appearance_code` from and toward ``start`` (None: the mean code),
    and of ``pose`` (in place) when given."""
    dev, field = trainer.device, trainer.field
    if rays_per_iteration is None:
        rays_per_iteration = FIT_RAYS_PER_ITERATION.get(dev.type, FIT_RAYS_PER_ITERATION["cuda"])
    _check_fit_inputs(trainer, c2w, intrinsics, width, height, image, distortion, iterations, rays_per_iteration,
                      pull)
    target_image = image.to(dev, torch.float32)
    c2w_n, intr_n = c2w.to(dev, torch.float32)[None], intrinsics.to(dev, torch.float32)[None]
    dist_n = None if distortion is None else distortion.to(dev, torch.float32)[None]
    px_all, py_all = (t.to(dev) for t in _left_half_pixels(width, height, iterations, rays_per_iteration, seed))

    def rays(px: torch.Tensor, py: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n = px.shape[0]
        return generate_rays(c2w_n.expand(n, 3, 4), intr_n.expand(n, 4),
                             None if dist_n is None else dist_n.expand(n, 6), px, py, fisheye=fisheye)

    with trainer.weights.averaged_in_field():
        codes = field.appearance.weight.detach()
        if start is not None and tuple(start.shape) != (codes.shape[1],):
            raise ValueError(f"start must be one code of {codes.shape[1]} values, got shape {tuple(start.shape)}")
        anchor = codes.mean(0) if start is None else start.detach().to(codes)
        code = anchor.clone().requires_grad_(True)
        adam = Adam([code], lr=lr)

        def distance(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:  # the fit's loss
            return (rgb - target).square().mean() + pull * (code - anchor).square().mean()

        if pose is None:
            _fit_code(trainer, code, adam, rays, px_all, py_all, target_image, background, distance)
            return code.detach()
        field_fn = _field_with_code_and_positions(field, code)
        pose_adam = Adam([pose.omega, pose.tau], lr=POSE_LR, eps=1e-15)
        pose_index = torch.zeros(px_all.shape[1], dtype=torch.long, device=dev)  # every ray: the one pose
        for it, (px, py) in enumerate(zip(px_all, py_all)):
            rays_o, rays_d = pose.rays(pose_index, *rays(px, py))
            with trainer.model.precision():
                bg = field.background(rays_d).detach() if background is None else background
                out = trainer.model.render(rays_o, rays_d, field_fn, background=bg, sigma_fn=field.density)
            if out["n_samples"] == 0:  # nothing along these rays: the code changes nothing
                continue
            loss = distance(out["rgb"], target_image[py, px])
            code.grad, pose.omega.grad, pose.tau.grad = torch.autograd.grad(loss, [code, pose.omega, pose.tau])
            pose_adam.param_groups[0]["lr"] = POSE_LR * (POSE_LR_FINAL / POSE_LR) ** (it / max(iterations - 1, 1))
            pose_adam.step()
            adam.step()
    return code.detach()


def _fit_code(trainer: Trainer, code: torch.Tensor, adam: Adam, rays, px_all: torch.Tensor, py_all: torch.Tensor,
              target_image: torch.Tensor, background: float | None, distance) -> None:
    """Adam on ``code`` alone, one iteration per row of ``px_all``, ``py_all`` [I, R], each
    minimising ``distance(rgb [R, 3], target [R, 3])`` (a 0-d tensor). A ray's
    sample weights do not depend on the code (σ does not), so the samples of
    :data:`FIT_GROUP_RAYS` rays at a time are marched and their geometry features computed once,
    and each iteration composites its rays' colours from them:

    .. math::

        C(r; e) = \\sum_i w_i\\, c(h_i, d_i, e) + (1 - O_r)\\, b_r

    the loss and gradient of rendering every iteration anew (up to summation order)."""
    field = trainer.field
    iterations, n = px_all.shape
    per_group = max(1, FIT_GROUP_RAYS // n)
    for first in range(0, iterations, per_group):
        px, py = px_all[first:first + per_group].reshape(-1), py_all[first:first + per_group].reshape(-1)
        rays_o, rays_d = rays(px, py)
        cache = {}

        def recording_fn(positions: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            sigma, h = field.geometry(positions)
            cache["h"], cache["directions"] = h, directions
            return sigma, torch.zeros_like(positions)  # the colours come below, with the code

        with torch.no_grad(), trainer.model.precision():
            bg = field.background(rays_d) if background is None else torch.full_like(rays_d, background)
            out = trainer.model.render(rays_o, rays_d, recording_fn, sigma_fn=field.density, return_samples=True)
        target = target_image[py, px]
        behind = (1.0 - out["opacity"])[:, None] * bg
        offsets = out["ray_offsets"].tolist()  # one host read per group
        for k in range(px.shape[0] // n):
            start, end = offsets[k * n], offsets[(k + 1) * n]
            if end == start:  # nothing along these rays: the code changes nothing
                continue
            with trainer.model.precision():
                colour = field.colour(cache["h"][start:end], cache["directions"][start:end], code, differentiable=True)
            rgb = behind[k * n:(k + 1) * n].index_add(0, out["ray_indices"][start:end] - k * n,
                                                      out["weights"][start:end, None] * colour.float())
            (code.grad,) = torch.autograd.grad(distance(rgb, target[k * n:(k + 1) * n]), [code])
            adam.step()
