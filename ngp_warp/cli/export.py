"""``ngp-warp export``: a mesh and/or a point cloud (PLY) of a trained run."""

from __future__ import annotations

from pathlib import Path

from ngp_warp.cli.common import CHECKPOINT, UserError, output_file, resolve_device

def add_export_parser(subparsers, positive_int, positive_float):
    """The ``export`` sub-command (``positive_int``/``positive_float``: the CLI's argparse
    types); returns its parser, for the CLI's shared ``--device``/``--quiet``."""
    x = subparsers.add_parser("export", help="export a trained output folder as a mesh and/or a point cloud (PLY)")
    x.add_argument("dir")
    x.add_argument("--mesh", metavar="OUT.ply", help="triangle mesh with vertex colours (relative to DIR)")
    x.add_argument("--resolution", type=positive_int, default=256,
                   help="marching-cubes nodes along the longest side of the occupied box (default 256)")
    x.add_argument("--threshold", type=positive_float,
                   help="density σ of the surface, per scene unit (default: instant-ngp's 2.5 per unit-cube side)")
    x.add_argument("--points", metavar="OUT.ply", help="coloured points at the training rays' expected depths")
    x.add_argument("--max-points", type=positive_int, default=2_000_000, help="keep at most this many points")
    x.add_argument("--scene", help="scene folder, if it moved since training")
    x.set_defaults(func=cmd_export)
    return x


def cmd_export(args) -> None:
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.outputs.export import default_threshold, extract_mesh, training_points  # Warp's geometry: export only
    from ngp_warp.outputs.ply import write_ply

    if not args.mesh and not args.points:
        raise UserError("export: nothing to export (give --mesh OUT.ply and/or --points OUT.ply)")
    out_dir = Path(args.dir)
    mesh_path = args.mesh and output_file(out_dir, args.mesh, "--mesh", (".ply",))
    points_path = args.points and output_file(out_dir, args.points, "--points", (".ply",))
    trainer, _ = load_trainer(out_dir / CHECKPOINT, device=resolve_device(args.device), scene_path=args.scene)
    world_from_scene = trainer.scene.world_from_scene
    if mesh_path:
        threshold = args.threshold or default_threshold(trainer.scene)
        field = trainer.field
        with trainer.weights.averaged_in_field():
            try:
                mesh = extract_mesh(field.density, lambda x, d: field(x, d)[1], field.aabb, threshold=threshold,
                                    resolution=args.resolution, grid=trainer.grid, world_from_scene=world_from_scene)
            except ValueError as e:
                raise UserError(f"--mesh: {e}") from None
        write_ply(mesh_path, mesh.vertices, mesh.colors, mesh.faces)
        print(f"wrote {mesh_path}: {mesh.vertices.shape[0]} vertices, {mesh.faces.shape[0]} triangles "
              f"(σ = {threshold:.4g})")
    if points_path:
        points, colors = training_points(trainer, args.max_points, world_from_scene)
        write_ply(points_path, points, colors)
        print(f"wrote {points_path}: {points.shape[0]} points")
