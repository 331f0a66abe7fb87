"""`jepa-envs lerobot bench`: export and import speed and memory beside an h5py read of the same frames."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm


def bench_lerobot(src: str | Path, codec: str = "lossless", progress: bool = False) -> dict:
    """Frames/s and peak memory of export and import beside an h5py read of the same frames, each phase in a
    fresh process (its own peak RSS), in one run (``progress``: a bar of the phases on stderr)."""
    src = Path(src).resolve()
    work = Path(tempfile.mkdtemp(prefix="jepa-lerobot-bench-"))
    phases = {
        "h5py read": f"import h5py\nfrom jepa_envs.datasets.hdf5 import demo_names\nf = h5py.File({str(src)!r})\n"
                     "n = 0\nfor d in demo_names(f['data']):\n    for k in f['data'][d]['obs']:\n"
                     "        x = f['data'][d]['obs'][k][()]\n        n += len(x) if x.dtype.name == 'uint8' else 0\n"
                     "frames = n",
        "export": f"from jepa_envs.datasets.lerobot import export_lerobot\n"
                  f"frames = export_lerobot({str(src)!r}, {str(work / 'ds')!r}, codec={codec!r})['frames']",
        "import": f"from jepa_envs.datasets.lerobot import import_lerobot\n"
                  f"frames = import_lerobot({str(work / 'ds')!r}, {str(work / 'back.hdf5')!r})['frames']",
    }
    out = {"src": str(src), "codec": codec, "load_average": os.getloadavg()[0], "phases": {}}
    try:
        for name, code in tqdm(phases.items(), desc="lerobot bench", unit="phase", disable=not progress):
            script = ("import json, resource, time\nt0 = time.perf_counter()\n" + code + "\n"
                      "print(json.dumps({'frames': frames, 'seconds': time.perf_counter() - t0, "
                      "'peak_rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))")
            done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
            row = json.loads(done.stdout.strip().splitlines()[-1])
            row["frames_per_s"] = row["frames"] / row["seconds"]
            out["phases"][name] = row
        out["dataset_mib"] = sum(p.stat().st_size for p in (work / "ds").rglob("*") if p.is_file()) / 2**20
        out["hdf5_mib"] = src.stat().st_size / 2**20
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out
