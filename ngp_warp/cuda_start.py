"""The CUDA driver started on a thread while torch imports: ``cuInit`` and the command's device's
primary context, through the driver library itself (ctypes). On an H200 host the two take
0.2–0.3 s that otherwise come after torch's import, inside Warp's initialisation and torch's
first CUDA call; both retain the same primary context, so they find it made. Imports neither
torch nor Warp. Nothing starts where there is no driver library or the command is bound for
the CPU, and a driver error leaves the start to torch and Warp, which report it."""

from __future__ import annotations

import ctypes
import os
import threading

GPU_COMMANDS = ("train", "demo", "fit-many", "eval", "render", "export", "view")
THREAD_NAME = "cuda start"


def device_ordinal(argv: list[str], local_rank: str | None = None) -> int | None:
    """The CUDA device that the command line ``argv`` (the words after ``ngp-warp``) will use:
    a rank's ``local_rank`` (``LOCAL_RANK``: ranks use ``cuda:LOCAL_RANK``,
    :func:`ngp_warp.training.distributed.join`) for any CUDA device, else N for ``--device
    cuda:N`` and 0 for ``cuda``, ``auto`` or no ``--device``; None for a command that uses no
    GPU, ``--device cpu`` or a value the parser will refuse."""
    if not argv or argv[0] not in GPU_COMMANDS:
        return None
    device = "auto"
    for word, following in zip(argv, argv[1:] + [""]):
        if word == "--device":
            device = following
        elif word.startswith("--device="):
            device = word.partition("=")[2]
    def number(text: str | None) -> int | None:
        return int(text) if text is not None and text.isascii() and text.isdecimal() else None

    kind, _, index = device.partition(":")
    if device == "auto" or kind == "cuda" and (index == "" or number(index) is not None):
        rank = number(local_rank)  # a rank uses cuda:LOCAL_RANK whatever --device names
        return rank if rank is not None else number(index) or 0
    return None


def _driver() -> ctypes.CDLL | None:
    name = "nvcuda.dll" if os.name == "nt" else "libcuda.so.1"
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


def _retain_primary_context(ordinal: int) -> None:
    """``cuInit`` and ``cuDevicePrimaryCtxRetain`` of device ``ordinal``; the context is kept for
    the process's life (torch and Warp retain it too)."""
    driver = _driver()
    if driver is None or driver.cuInit(0) != 0:
        return
    device, context = ctypes.c_int(), ctypes.c_void_p()
    if driver.cuDeviceGet(ctypes.byref(device), ordinal) == 0:
        driver.cuDevicePrimaryCtxRetain(ctypes.byref(context), device)


def start_cuda(argv: list[str]) -> threading.Thread | None:
    """Start the driver for the command ``argv`` on a daemon thread (ctypes releases the GIL
    while the driver works, so torch's import goes on beside it); the thread, or None when the
    command uses no GPU (:func:`device_ordinal`) or ``CUDA_VISIBLE_DEVICES`` hides every GPU."""
    ordinal = device_ordinal(argv, os.environ.get("LOCAL_RANK"))
    if ordinal is None or os.environ.get("CUDA_VISIBLE_DEVICES", None) in ("", "-1"):
        return None
    # what torch sets before its own CUDA start, read by cuInit: kernels loaded on first use
    os.environ.setdefault("CUDA_MODULE_LOADING", "LAZY")
    thread = threading.Thread(target=_retain_primary_context, args=(ordinal,), name=THREAD_NAME, daemon=True)
    thread.start()
    return thread
