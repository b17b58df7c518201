"""A scene's images decoded by a child process while the command imports torch.

``ngp-warp train SCENE`` calls :func:`start_prefetch` before anything imports torch, on a machine
of :data:`MIN_CORES` usable cores or more: a child Python (``python -m ngp_warp.data.prefetch``,
numpy and Pillow only) decodes the image files that :func:`~ngp_warp.data.loading.load_scene`
will read on threads of its own, writes their pixels one after another into an unlinked
temporary file (in ``/dev/shm`` where it has room), and prints an index of them. Threads of the
command itself would hold up torch's import on the GIL by about what they save; a process does
not. :func:`collect_prefetched` waits for the child, and :func:`read_prefetched` gives the
loading each image from that file where its file is unchanged since (:func:`_file_key`) and reads
it itself otherwise, so a problem with a file (unreadable, corrupt, changed) is the loading's to
raise, as without a prefetch.
:func:`drop_prefetched` forgets what the loading did not take. Imports neither torch nor Warp.

On a machine with fewer cores the child would take the cores that torch's import needs (on 2
cores, decoding beside torch's import delayed everything after it by as much as it saved), so
nothing starts.
"""

from __future__ import annotations

import json
import mmap
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

MIN_CORES = 8  # usable cores for a prefetch: the child's decoders beside torch's import
MAX_BYTES = 2 << 30  # decoded pixels the child writes at most; the loading reads the rest itself
DECODERS = 16  # the child's decoding threads at most
# numpy, Pillow and the scene's readers load inside the functions: the command starts the child
# before importing anything it can leave for later

_child: tuple[subprocess.Popen, object] | None = None  # the running child and its file
_decoded: dict | None = None  # path → (file key, pixels)
_lock = threading.Lock()  # the loading reads on several threads


def usable_cores() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _file_key(path: Path) -> list[int]:
    """What tells a file unchanged: its size, modification and change times, inode and device
    (a copy that keeps the size and the modification time still changes the change time)."""
    stat = os.stat(path)
    return [stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino, stat.st_dev]


def _spool_dir(max_bytes: int) -> str | None:
    """/dev/shm where it can take ``max_bytes`` (a container's is often 64 MB), else None: the
    system's temporary folder."""
    shm = "/dev/shm"
    try:
        roomy = os.access(shm, os.W_OK) and shutil.disk_usage(shm).free >= max_bytes
    except OSError:
        roomy = False
    return shm if roomy else None


def start_prefetch(scene: str | Path, downscale: int = 1, min_cores: int | None = None,
                   max_bytes: int = MAX_BYTES) -> bool:
    """Start the child that decodes the images of ``scene`` at ``downscale`` (see the module), on
    a POSIX machine of at least ``min_cores`` (default :data:`MIN_CORES`) usable cores, writing
    at most ``max_bytes`` of pixels; True when it started. A second call drops the first one's
    child."""
    drop_prefetched()
    if os.name != "posix" or usable_cores() < (MIN_CORES if min_cores is None else min_cores):
        return False
    global _child
    try:
        spool = tempfile.TemporaryFile(dir=_spool_dir(max_bytes))
        # -P: the package the command runs, not one in the current folder
        child = subprocess.Popen([sys.executable, "-P", "-m", "ngp_warp.data.prefetch", str(scene), str(downscale),
                                  str(spool.fileno()), str(max_bytes)], pass_fds=(spool.fileno(),),
                                 stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    except OSError:
        return False
    _child = (child, spool)
    return True


def _map(fd: int) -> mmap.mmap:
    """The file ``fd`` mapped read-only, its pages mapped at once where the system can
    (``MAP_POPULATE``: a page fault for each 4 KiB of lego's 192 MB of pixels cost 0.3 s)."""
    if hasattr(mmap, "MAP_POPULATE"):
        return mmap.mmap(fd, 0, flags=mmap.MAP_SHARED | mmap.MAP_POPULATE, prot=mmap.PROT_READ)
    return mmap.mmap(fd, 0, access=mmap.ACCESS_READ)


def _decoded_pixels(index: list, pixels) -> dict:
    import numpy as np

    decoded = {}
    for path, key, shape, offset in index:
        count = int(np.prod(shape))
        decoded[path] = (key, np.frombuffer(pixels, np.uint8, count, offset).reshape(shape))
    return decoded


def collect_prefetched() -> None:
    """Wait for the child, on the calling thread (a Ctrl-C meanwhile ends the child at once),
    and map what it wrote for :func:`read_prefetched`: {path: (file key, [H, W, C] uint8
    read-only ndarray)}, nothing where it failed. Nothing to do without a child."""
    global _child, _decoded
    with _lock:
        if _child is None:
            return
        child, spool = _child
        _child = None
    try:
        index_text = child.communicate()[0]
    except BaseException:
        child.kill()
        child.wait()
        spool.close()
        raise
    with spool:
        try:
            index = json.loads(index_text) if child.returncode == 0 else []
            decoded = _decoded_pixels(index, _map(spool.fileno())) if index else {}
        except (ValueError, TypeError, OSError):  # an index this module did not write
            decoded = {}
    with _lock:
        _decoded = decoded


def read_prefetched(path: Path):
    """:func:`~ngp_warp.data.images.read_image` of ``path`` ([H, W, 3 or 4] uint8; read-only
    when it comes from the prefetch): the child's pixels when it decoded this file and the file
    is unchanged since (:func:`_file_key`), else a read of the file. Waits for the child first
    where :func:`collect_prefetched` has not."""
    from ngp_warp.data.images import read_image

    collect_prefetched()
    with _lock:
        key, pixels = (_decoded or {}).pop(str(path), (None, None))
    try:
        unchanged = pixels is not None and _file_key(path) == key
    except OSError:
        unchanged = False
    return pixels if unchanged else read_image(path)


def drop_prefetched() -> None:
    """Forget the prefetch: end a child still running and let go of what the loading did not take."""
    global _child, _decoded
    with _lock:
        if _child is not None:
            child, spool = _child
            child.kill()
            child.communicate()
            spool.close()
        _child, _decoded = None, None


def _write_all(fd: int, data: memoryview) -> None:
    while data:
        data = data[os.write(fd, data):]


def _decode_scene(scene: Path, downscale: int, spool_fd: int, max_bytes: int) -> list:
    """The child's work: decode the scene's images on threads, write their pixels to
    ``spool_fd`` in turn (until ``max_bytes``, or the file system is full), and return the index
    [path, file key, shape, offset] of those written. Files it cannot list or decode are
    left out."""
    import numpy as np

    from ngp_warp.data.data_error import DataError
    from ngp_warp.data.images import read_image
    from ngp_warp.data.scene_sources import scene_image_files

    try:
        files = list(dict.fromkeys(scene_image_files(scene, downscale)))
    except (DataError, OSError, ValueError):
        return []

    def decode(path: Path):
        try:
            return _file_key(path), read_image(path)
        except (DataError, OSError):
            return None, None

    index, offset, parent = [], 0, os.getppid()
    pool = ThreadPoolExecutor(min(DECODERS, usable_cores()))
    try:
        for path, (key, pixels) in zip(files, pool.map(decode, files)):
            if os.getppid() != parent or offset + (0 if pixels is None else pixels.nbytes) > max_bytes:
                break  # the command has ended (say, on a mistyped option), or the bytes are spent
            if pixels is None:
                continue
            try:
                _write_all(spool_fd, memoryview(np.ascontiguousarray(pixels)).cast("B"))
            except OSError:  # the file system is full: what is written so far stands
                break
            index.append([str(path), key, list(pixels.shape), offset])
            offset += pixels.nbytes
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        os.close(spool_fd)
    return index


if __name__ == "__main__":  # the child: SCENE DOWNSCALE FD MAX_BYTES
    print(json.dumps(_decode_scene(Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))))
