"""When Dask pays: ``oapcal correct`` streaming against ``--dask`` on this machine.

One TIFF stack (``--frames`` frames of ``--size`` px, uint16, uncompressed; in a temporary
directory) is corrected through the library calls behind ``oapcal correct``:

1. streaming (``correct_stack``, the command without ``--dask``: frame by frame, one
   process, OpenCV's own threads), TIFF out;
2. ``correct_stack_dask`` with the default ``engine="auto"`` and no scheduler (what
   ``--dask`` now does with one worker: the frames streamed in this process without Dask,
   into the same output);
3. Dask's ``threads`` scheduler (one process, a thread pool);
4. ``engine="dask"``, N = 1, 2, 4 workers: a new ``LocalCluster`` of N single-threaded
   worker processes talking over loopback TCP (what ``--dask --workers N`` does; before this
   change also N = 1), its start-up included;
5. an already running loopback cluster (``dask scheduler`` and N ``dask worker`` processes
   on 127.0.0.1 started before the timing, as a cluster would be), N = 1, 2, 4.

Dask runs write ``NAME.zarr`` unless ``--format tiff``; every output is compared with the
streaming one (identical, or the run fails).  Times are wall-clock medians of
``--repeats`` runs.  Run it under ``nice -n 10`` on a shared machine:

    PYTHONPATH=src nice -n 10 python benchmarks/bench_dask.py [--frames 300] [--size 1024]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from oapcal.batch.distributed import DaskSettings, correct_stack_dask, dask_scheduler
from oapcal.batch.stack import correct_stack
from oapcal.calibration import Calibration, FitSummary
from oapcal.model import PRESETS, scale_params
from oapcal.stats import ResidualStats
from oapcal.synthetic import EXAMPLE_TRUTH


def calibration(size: int) -> Calibration:
    free = PRESETS["paper"]
    return Calibration(free=free, params=scale_params(EXAMPLE_TRUTH, 640 / size), stderr=np.full(13, np.nan),
                       covariance=np.zeros((len(free), len(free))),
                       fit=FitSummary(n_points=1, rss=0.0, converged=True),
                       residuals=ResidualStats(*[float("nan")] * 4, n_points=0),
                       um_per_px=4.8, image_size=(size, size), name="bench")  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def loopback_cluster(n_workers: int):
    """``dask scheduler`` and ``n_workers`` ``dask worker`` processes on 127.0.0.1; yields the address."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    bindir = Path(sys.executable).parent
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([bindir / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], **quiet)]  # fmt: skip
    try:
        time.sleep(2)
        for _ in range(n_workers):
            worker = [bindir / "dask", "worker", address, "--nthreads", "1", "--nworkers", "1",
                      "--no-dashboard", "--memory-limit", "0"]  # fmt: skip
            procs.append(subprocess.Popen(worker, **quiet))
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(n_workers, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(10)


def run(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def read_output(out: Path, stem: str) -> np.ndarray:
    if (out / f"{stem}.zarr").exists():
        import zarr

        return zarr.open_array(str(out / f"{stem}.zarr"), mode="r")[:]
    return tifffile.imread(out / f"{stem}.tif")


def main_bench():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--chunk-frames", type=int, default=16)
    ap.add_argument("--format", choices=["zarr", "tiff"], default="zarr")
    ap.add_argument("--skip-cluster", action="store_true", help="no separately started loopback cluster")
    args = ap.parse_args()
    import cv2
    import dask

    workers = [int(w) for w in args.workers.split(",") if w]  # --workers "" : streaming and threads only
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; OpenCV {cv2.__version__} "
          f"({cv2.getNumThreads()} threads), dask {dask.__version__}")  # fmt: skip
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rng = np.random.default_rng(0)
        src = tmp / "stack.tif"
        with tifffile.TiffWriter(src) as tw:
            for _ in range(args.frames):
                tw.write(rng.integers(0, 4096, (args.size, args.size), dtype=np.uint16), contiguous=True)
        mb = args.frames * args.size * args.size * 2 / 1e6
        print(f"stack: {args.frames} frames of {args.size}x{args.size} uint16 ({mb:.0f} MB), chunks of "
              f"{args.chunk_frames} frames, dask output {args.format}")  # fmt: skip
        cal = calibration(args.size)
        reference = None

        def measure(label, fn, out_name):
            nonlocal reference
            out = tmp / out_name
            times = []
            for _ in range(args.repeats):
                shutil.rmtree(out, ignore_errors=True)
                times.append(run(lambda: fn(out)))
            result = read_output(out, "stack")
            if reference is None:
                reference = result
            assert np.array_equal(result, reference), f"{label}: output differs from streaming"
            shutil.rmtree(out, ignore_errors=True)
            t = statistics.median(times)
            rows.append((label, t))
            print(f"{label:58s} {t:7.2f} s  {args.frames / t:7.1f} frames/s  "
                  f"({', '.join(f'{x:.2f}' for x in times)})", flush=True)  # fmt: skip

        def stream(out):
            report = correct_stack(cal, [src], out)
            assert report.ok, report.results

        def with_dask(**kw):
            settings = DaskSettings(chunk_frames=args.chunk_frames, output_format=args.format, **kw)
            return lambda out: correct_stack_dask(cal, src, out, None, settings)

        measure("streaming (correct without --dask)", stream, "stream")
        measure("--dask, engine auto (one worker): streamed in-process", with_dask(), "auto")
        measure("--dask --scheduler threads", with_dask(scheduler="threads"), "threads")
        for n in workers:
            label = f"--dask --workers {n}: new LocalCluster (loopback TCP)"
            measure(label, with_dask(workers=n, engine="dask"), f"lc{n}")
        if not args.skip_cluster:
            for n in workers:
                with loopback_cluster(n) as address, dask_scheduler(address) as session:
                    settings = DaskSettings(chunk_frames=args.chunk_frames, output_format=args.format,
                                            scheduler=address)  # fmt: skip

                    def on_cluster(out, settings=settings, session=session):
                        correct_stack_dask(cal, src, out, None, settings, session=session)

                    measure(
                        f"--dask --scheduler tcp://127.0.0.1:PORT ({n} workers running)", on_cluster, f"cl{n}"
                    )
    stream = rows[0][1]
    print("\nratio to streaming:")
    for label, t in rows:
        print(f"  {label:52s} {t / stream:5.2f}x")


if __name__ == "__main__":
    main_bench()
