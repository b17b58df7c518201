"""``ngp-warp view``: the web viewer of a run, or of a scene trained live."""

from __future__ import annotations

import errno
import os
import socket
import sys
from pathlib import Path

from ngp_warp.outputs.camera_path import MAX_SIDE
from ngp_warp.cli.common import (CHECKPOINT, MAX_DOWNSCALE, UserError, check_run_apart, new_trainer, positive,
                                 refuse_probe, resolve_device, run_saver, seed_number, train_config)


def add_view_parser(subparsers):
    """The ``view`` sub-command; returns its parser, for the CLI's shared ``--device``/``--quiet``."""
    v = subparsers.add_parser("view", help="web viewer (viser) of a trained output folder, or of a scene trained live")
    v.add_argument("target", metavar="RUN_OR_SCENE", help="a trained output folder, or a scene folder to train live")
    v.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; forward it over SSH: ssh -L 8080:localhost:8080)")
    v.add_argument("--port", type=positive(int, high=65535), default=8080, help="port (default 8080)")
    v.add_argument("--resolution", type=positive(int, high=MAX_SIDE),
                   help="longest side of a resting frame in pixels (default 800 on CUDA, 200 on the CPU)")
    v.add_argument("--moving-resolution", type=positive(int, high=MAX_SIDE),
                   help="longest side while the camera moves (default a quarter of --resolution)")
    v.add_argument("--scene", help="a run's scene folder, if it moved since training")
    v.add_argument("--steps", type=positive(int), help="live training: steps (default 20000)")
    v.add_argument("--seconds", type=positive(float), help="live training: wall-clock budget in seconds")
    v.add_argument("--downscale", type=positive(int, high=MAX_DOWNSCALE), default=1, help="live training: shrink images by this factor")
    v.add_argument("--seed", type=seed_number, default=0)
    v.add_argument("--target-samples", type=positive(int), help="live training: samples per batch")
    v.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="live training: any setting")
    v.add_argument("--out", help="live training: keep the run in this folder when the viewer stops (Ctrl-C): "
                                 "its checkpoint, as ngp-warp train saves it (then ngp-warp eval, view, render it)")
    v.add_argument("--overwrite", action="store_true", help="live training: replace the run that --out holds")
    v.set_defaults(func=cmd_view)
    return v


def load_target(args, device: str):
    """(trainer, live) for ``args.target``: a run folder's checkpoint, or a scene to train live."""
    from ngp_warp.training.checkpoint import load_trainer
    from ngp_warp.data.loading import load_scene

    target = Path(args.target)
    if (target / CHECKPOINT).is_file():
        given = {"--steps": None, "--seconds": None, "--downscale": 1, "--seed": 0, "--target-samples": None, "--set": [],
                 "--out": None, "--overwrite": False}
        live_only = [flag for flag, unset in given.items() if getattr(args, flag[2:].replace("-", "_"), unset) != unset]
        if live_only:
            raise UserError(f"{', '.join(live_only)}: settings of live training, but {target} is a trained run "
                            f"(give a scene folder to train one live)")
        return load_trainer(target / CHECKPOINT, device=device, scene_path=args.scene)[0], False
    if not target.exists():
        raise UserError(f"{target}: no such run or scene folder")
    config = train_config(args, device)  # bad settings before the scene is read
    refuse_probe(config, "by view (it trains live)")
    return new_trainer(load_scene(target, downscale=args.downscale), config, device), True


def live_run_folder(args):
    """The :class:`RunFolder` of ``--out`` for a scene trained live (None without ``--out``);
    one-line errors, before anything trains, where the folder cannot take the run. Nothing is
    created until the run is saved."""
    from ngp_warp.training.run_folder import RunFolder

    if args.out is None:
        if args.overwrite:
            raise UserError("--overwrite: replaces the run --out holds, but no --out is given")
        return None
    out = Path(args.out)
    check_run_apart(out, Path(args.target))
    folder = RunFolder(out, overwrite=args.overwrite, flags=(None, "--overwrite"))  # main reports its errors
    existing = next(p for p in (out, *out.absolute().parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"--out {out}: cannot write there ({existing} is not a writable folder)")
    return folder


def keep_live_run(trainer, folder, args) -> None:
    """Save the live run into ``folder`` (a :class:`RunFolder`), saying where, or why not."""
    from ngp_warp.training.checkpoint import NonFiniteWeights

    if trainer.step_count == 0:
        print(f"ngp-warp view: nothing trained; nothing written to {folder.path}", file=sys.stderr)
        return
    try:
        run_saver(trainer, folder, Path(args.target), args.downscale)()
    except NonFiniteWeights:
        print(f"ngp-warp view: the live run diverged (weights not finite); nothing written to {folder.path}",
              file=sys.stderr)
        return
    print(f"ngp-warp view: the live run saved at step {trainer.step_count} to {folder.path} "
          f"(score it with ngp-warp eval {folder.path})", file=sys.stderr)


def port_in_use(host: str, port: int) -> UserError:
    return UserError(f"--port {port}: already in use on {host} (choose another --port, and forward that one)")


def check_listen_address(host: str, port: int) -> None:
    """UserError (one line) unless a server can listen on ``host``:``port`` now: a host this
    machine has, a port nobody else holds (another port would break SSH forwarding)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as e:
        raise UserError(f"--host {host}: not an address to listen on ({getattr(e, 'strerror', None) or e})") from None
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: a closed port is free
        try:
            probe.bind(address)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise port_in_use(host, port) from None
            raise UserError(f"--host {host} --port {port}: cannot listen there ({e.strerror or e})") from None


def cmd_view(args) -> None:

    try:
        import viser  # noqa: F401  (the viewer extra)
    except ImportError:
        raise UserError("view needs viser: pip install 'ngp-warp[viewer]'") from None
    from ngp_warp.viewer.server import Viewer

    check_listen_address(args.host, args.port)  # before the run is loaded
    device = resolve_device(args.device)
    folder = None if (Path(args.target) / CHECKPOINT).is_file() else live_run_folder(args)  # before the scene loads
    trainer, live = load_target(args, device)
    resolution = args.resolution or (800 if trainer.device.type == "cuda" else 200)
    moving = args.moving_resolution or max(16, resolution // 4)
    try:
        viewer = Viewer(trainer, args.host, args.port, resolution, moving, live)
    except OSError as e:
        raise UserError(f"--port {args.port}: cannot listen on {args.host} ({e.strerror or e})") from None
    if viewer.server.get_port() != args.port:  # taken since the check: the server moved to another
        viewer.close()
        raise port_in_use(args.host, args.port)
    what = f"step {trainer.step_count}" if not live else "training live" if folder else \
        "training live, not kept: --out DIR keeps it"
    print(f"ngp-warp view: {args.target} ({what}) at {viewer.url}  (Ctrl-C to stop)", file=sys.stderr)
    print(viewer.url, flush=True)
    interrupted = False
    try:
        viewer.serve()
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (main's sigterm_as_interrupt): the way a viewer stops
        interrupted = True
        raise
    finally:
        viewer.close()
        if interrupted and folder is not None:  # not after a failed step: its state may be broken
            keep_live_run(trainer, folder, args)
