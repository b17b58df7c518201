"""Throughput of the hash-grid encoding: forward, backward and forward+backward.

    python benchmarks/bench_hashgrid.py --device cuda --sizes 2^16,2^18,2^20,2^21,2^22
    python benchmarks/bench_hashgrid.py --device cuda --sizes 2^21 --variants default k2 k8 nopair fp16
    python benchmarks/bench_hashgrid.py --device cpu --sizes 2^12,2^14 --repeats 3

Default configuration: the NeRF one (D=3, L=16, F=2, T=2^19, base 16, per-level scale 2),
random points in the unit cube (the worst case for the caches: real NeRF batches are
spatially coherent). Columns, per size and variant, in million points per second:

* ``fwd``: forward only (``torch.no_grad``);
* ``bwd``: backward to the table only (``torch.autograd.grad`` w.r.t. ``params``);
* ``f+b``: forward then that backward;
* ``bwdx``: backward to the input only (with ``--with-dx``);
* ``GB/s``: effective bandwidth of fwd / bwd, counting the points read once, the output (or
  its gradient) once and every corner access as ``F*4`` bytes (the gathers of the forward, the
  atomic additions of the backward): ``N*(D*4 + L*F*4 + L*2^D*F*4)`` bytes;
* ``ref`` / ``x``: the pure-torch reference (``ngp_warp/_reference/hashgrid.py``) in float32 on
  the same device, same run, and the speed-up of the Warp kernels over it.

Times are medians over ``--repeats`` batches of ``--inner`` back-to-back calls after warm-up
(CUDA events around each batch on a GPU, so that the host-side cost of a call overlaps the
GPU work of the previous ones as in training; ``perf_counter`` on the CPU); the reference
is timed the same way, over fewer batches. Variants (``--variants``; tokens joined by ``+``) set the
CUDA scheduling knobs of ``HashGridEncoding``: ``kN`` lanes per point (one level each),
``gN`` levels per thread, ``pair`` / ``nopair`` x-pair merged table-gradient reductions,
``gxN`` levels per input-gradient thread (``gx0``: all), ``fp16`` half-precision
table-gradient accumulation.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ngp_warp import HashGridEncoding  # noqa: E402
from ngp_warp._reference.hashgrid import encode_like  # noqa: E402
from ngp_warp.outputs.bench import device_name, measure  # noqa: E402


def parse_sizes(text: str) -> list[int]:
    sizes = []
    for tok in text.split(","):
        tok = tok.strip()
        if not tok:
            continue
        sizes.append(2 ** int(tok[2:]) if tok.startswith("2^") else int(tok))
    return sizes


KNOBS = (
    "cuda_level_lanes",
    "cuda_levels_per_thread",
    "cuda_paired",
    "cuda_dx_levels_per_thread",
    "grad_dtype",
)


def apply_variant(enc: HashGridEncoding, variant: str, defaults: dict) -> None:
    for k, v in defaults.items():
        setattr(enc, k, v)
    if variant == "default":
        return
    for tok in variant.split("+"):
        if tok == "pair":
            enc.cuda_paired = True
        elif tok == "nopair":
            enc.cuda_paired = False
        elif tok == "fp16":
            enc.grad_dtype = torch.float16
        elif tok.startswith("k"):
            enc.cuda_level_lanes = int(tok[1:])
        elif tok.startswith("gx"):
            enc.cuda_dx_levels_per_thread = int(tok[2:])
        elif tok.startswith("g"):
            enc.cuda_levels_per_thread = int(tok[1:])
        else:
            raise SystemExit(f"unknown variant token {tok!r}")


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--sizes", default=None, help="comma-separated N, e.g. 2^16,2^21 or 65536")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--inner", type=int, default=None, help="calls per timed batch (GPU default 5, CPU 1)")
    ap.add_argument("--variants", nargs="+", default=["default"])
    ap.add_argument("--dims", type=int, default=3)
    ap.add_argument("--levels", type=int, default=16)
    ap.add_argument("--features", type=int, default=2)
    ap.add_argument("--log2-hashmap-size", type=int, default=19)
    ap.add_argument("--base-resolution", type=int, default=16)
    ap.add_argument("--per-level-scale", type=float, default=2.0)
    ap.add_argument("--interpolation", default="linear")
    ap.add_argument("--with-dx", action="store_true", help="also time the input-gradient backward")
    ap.add_argument("--no-reference", action="store_true", help="skip the pure-torch reference")
    ap.add_argument("--reference-max-size", type=int, default=2**22)
    ap.add_argument("--json", default=None, help="write all numbers to this file")
    return ap.parse_args(argv)


def run_header(enc: HashGridEncoding, device: torch.device, repeats: int, inner: int) -> dict:
    """Date, commit, device, versions and configuration of this run (also printed)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = ""
    header = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "commit": commit,
        "device": device_name(device),
        "torch": torch.__version__,
        "warp": __import__("warp").__version__,
        "config": {
            "D": enc.n_input_dims,
            "L": enc.n_levels,
            "F": enc.n_features_per_level,
            "log2T": enc.log2_hashmap_size,
            "base": enc.base_resolution,
            "per_level_scale": enc.per_level_scale,
            "interpolation": enc.interpolation,
        },
        "command": " ".join(sys.argv),
        "repeats": repeats,
        "inner": inner,
    }
    print(f"# {header['device']}  torch {header['torch']}  warp {header['warp']}  commit {commit}  {header['date']}")
    print(f"# D={enc.n_input_dims} L={enc.n_levels} F={enc.n_features_per_level} T=2^{enc.log2_hashmap_size} "
          f"n_params={enc.n_params}  repeats={repeats} x {inner} calls")
    return header


def measure_rows(enc: HashGridEncoding, args, sizes: list[int], device, repeats: int, inner: int) -> list[dict]:
    """Seconds per call of every size and variant (and of the reference, once per size)."""
    rows = []
    ref_cache = {}
    defaults = {k: getattr(enc, k) for k in KNOBS}
    for n in sizes:
        for variant in args.variants:
            apply_variant(enc, variant, defaults)
            t = measure(enc, lambda x, p: enc(x), enc.params, n, device, repeats, args.warmup, inner, args.with_dx)
            row = {"n": n, "variant": variant, **t}
            if not args.no_reference and n <= args.reference_max_size:
                if n not in ref_cache:
                    ref_params = enc.params.detach().clone().requires_grad_()
                    ref_cache[n] = measure(
                        enc,
                        lambda x, p: encode_like(enc, x, p, dtype=torch.float32),
                        ref_params,
                        n,
                        device,
                        max(3, repeats // 4),
                        1,
                        inner,
                        False,
                    )
                row.update({f"ref_{k}": v for k, v in ref_cache[n].items()})
            rows.append(row)
    return rows


def mpts(n, s):
    return n / s * 1e-6


def print_table(rows: list[dict], args, bytes_per_point: int) -> None:
    """Print the rows in Mpoints/s and add the ``*_mpts`` columns to them."""
    cols = ["N", "variant", "fwd", "bwd", "f+b"] + (["bwdx"] if args.with_dx else []) + ["fwd GB/s", "bwd GB/s"]
    if not args.no_reference:
        cols += ["ref fwd", "ref bwd", "ref f+b", "x fwd", "x bwd", "x f+b"]
    print("# Mpoints/s (GB/s effective; x = speed-up over the pure-torch reference)")
    print(" | ".join(f"{c:>10}" for c in cols))
    for r in rows:
        n = r["n"]
        vals = [f"2^{n.bit_length() - 1}" if n & (n - 1) == 0 else str(n), r["variant"]]
        vals += [f"{mpts(n, r[k]):.1f}" for k in ("fwd_s", "bwd_s", "fb_s")]
        if args.with_dx:
            vals.append(f"{mpts(n, r['bwdx_s']):.1f}")
        vals += [f"{n * bytes_per_point / r[k] * 1e-9:.0f}" for k in ("fwd_s", "bwd_s")]
        if not args.no_reference:
            if "ref_fwd_s" in r:
                vals += [f"{mpts(n, r['ref_' + k]):.2f}" for k in ("fwd_s", "bwd_s", "fb_s")]
                vals += [f"{r['ref_' + k] / r[k]:.1f}" for k in ("fwd_s", "bwd_s", "fb_s")]
            else:
                vals += ["-"] * 6
        print(" | ".join(f"{v:>10}" for v in vals))
        r.update({f"{k[:-2]}_mpts": mpts(n, r[k]) for k in list(r) if k.endswith("_s")})


def main(argv=None) -> int:
    args = parse_args(argv)
    device = torch.device(args.device)
    is_cuda = device.type == "cuda"
    default_sizes = [2**k for k in (16, 18, 20, 21, 22)] if is_cuda else [2**12, 2**14]
    sizes = parse_sizes(args.sizes) if args.sizes else default_sizes
    repeats = args.repeats or (20 if is_cuda else 3)
    inner = args.inner or (5 if is_cuda else 1)
    enc = HashGridEncoding(
        args.dims,
        args.levels,
        args.features,
        args.log2_hashmap_size,
        args.base_resolution,
        args.per_level_scale,
        args.interpolation,
        device=device,
    )
    D, L, F = enc.n_input_dims, enc.n_levels, enc.n_features_per_level
    bytes_per_point = D * 4 + L * F * 4 + L * (1 << D) * F * 4
    header = run_header(enc, device, repeats, inner)
    rows = measure_rows(enc, args, sizes, device, repeats, inner)
    print_table(rows, args, bytes_per_point)
    if args.json:
        Path(args.json).write_text(json.dumps({**header, "bytes_per_point": bytes_per_point, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
