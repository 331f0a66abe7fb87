"""Which OpenGL path MuJoCo renders with, measured on this machine rather than assumed.

MuJoCo picks its offscreen backend from ``MUJOCO_GL`` (``egl``, ``osmesa``, ``glfw``) when it is first imported.
``choose_renderer`` honours a ``MUJOCO_GL`` the user set; otherwise it renders the same frames of a robosuite
scene (Square's two 84 px cameras; a small built-in scene without robosuite) through each backend that works
here, in a child process per backend, and picks the fastest whose frames are identical to the reference
(OSMesa, what this toolkit's datasets were rendered with; EGL over Mesa's llvmpipe on a CPU machine, over the
GPU's driver on a GPU machine). The choice is cached per machine in ``~/.cache/jepa_policy/renderer.json`` and
printed once. ``jepa-envs bench --renderers`` prints the measurement.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

from tqdm import tqdm

CANDIDATES = ("egl", "osmesa")
REFERENCE = "osmesa"
MARGIN = 0.10        # a backend other than the reference must be this much faster per frame to be chosen
_chosen_by = ""      # "you" (MUJOCO_GL was set) or "measured", once use_renderer ran
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jepa_policy" / "renderer.json"

_PROBE = r"""
import hashlib, json, os, sys, time
import numpy as np
frames = int(sys.argv[1]); size = int(sys.argv[2])
try:
    import gymnasium as gym, jepa_envs
    env = gym.make("JEPA/Square-v0", image_size=size)
    env.reset(seed=0)
    sim = env.unwrapped.backend.sim
    cameras = ["agentview", "robot0_eye_in_hand"]
    render = lambda i: sim.render(camera_name=cameras[i % 2], width=size, height=size, depth=False)
    scene = "Square (robosuite), 2 cameras"
except ImportError:
    import mujoco
    xml = ('<mujoco><worldbody><light pos="0 0 3"/><geom type="plane" size="2 2 .1" rgba=".8 .8 .8 1"/>'
           + "".join(f'<body pos="{x/4} {y/4} .3"><geom type="capsule" size=".05 .1" rgba="{x/8} .3 {y/8} 1"/></body>'
                     for x in range(-3, 4) for y in range(-3, 4))
           + '<camera name="top" pos="0 -2 2" xyaxes="1 0 0 0 .7 .7"/></worldbody></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml); data = mujoco.MjData(model); mujoco.mj_forward(model, data)
    renderer = mujoco.Renderer(model, size, size)
    def render(i):
        renderer.update_scene(data, camera="top")
        return renderer.render()
    scene = "built-in MuJoCo scene"
digest = hashlib.sha256(b"".join(render(i).tobytes() for i in range(2))).hexdigest()
times = []
for i in range(frames):
    t0 = time.perf_counter(); render(i); times.append(time.perf_counter() - t0)
print(json.dumps({"ms_per_frame": float(np.median(times) * 1e3), "digest": digest, "scene": scene}))
"""


def probe(renderer: str, frames: int = 20, size: int = 84, extra_env: dict | None = None,
          timeout_s: float = 300.0) -> dict:
    """Render ``frames`` frames through ``renderer`` in a child process: ms per frame and a digest of the frames;
    ``{"error": ...}`` when the backend does not work here."""
    env = {**os.environ, "MUJOCO_GL": renderer, "PYOPENGL_PLATFORM": renderer, **(extra_env or {})}
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE, str(frames), str(size)], env=env, capture_output=True,
                             text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"renderer": renderer, "error": f"no answer within {timeout_s:.0f}s"}
    lines = [line for line in out.stdout.splitlines() if line.startswith("{")]
    if out.returncode != 0 or not lines:
        last = (out.stderr.strip().splitlines() or ["exited without output"])[-1]
        return {"renderer": renderer, "error": last[:300]}
    return {"renderer": renderer, **json.loads(lines[-1])}


# where EGL vendor libraries (libEGL_mesa, libEGL_nvidia) are installed; one directory level, not a walk of
# /usr/lib, which took 1.4 s here at every start of a process that renders
EGL_LIBRARY_GLOBS = ("/usr/lib/libEGL_*.so*", "/usr/lib/*/libEGL_*.so*", "/usr/lib64/libEGL_*.so*")


def _machine_key() -> str:
    libs = sorted(p for pattern in EGL_LIBRARY_GLOBS for p in glob.glob(pattern))
    # the mujoco version from its metadata: ``import mujoco`` would fix the backend before the choice
    raw = json.dumps([platform.node(), platform.machine(), version("mujoco"), os.cpu_count(), libs])
    return hashlib.sha256(raw.encode()).hexdigest()[:16]


def measure(frames: int = 20, size: int = 84) -> dict:
    """Probe every candidate; returns {"results": [...], "choice": name, "why": text}."""
    results = [probe(name, frames, size) for name in CANDIDATES]
    working = [r for r in results if "error" not in r]
    if not working:
        return {"results": results, "choice": REFERENCE, "why": "no backend rendered here; keeping osmesa"}
    reference = next((r for r in working if r["renderer"] == REFERENCE), working[0])
    same = [r for r in working if r["digest"] == reference["digest"]]
    # another backend replaces the reference only when clearly faster (one probe is noisy on a loaded machine)
    best = min(same, key=lambda r: r["ms_per_frame"] * (1.0 if r is reference else 1.0 / (1.0 - MARGIN)))
    others = ", ".join(f"{r['renderer']} {r['ms_per_frame']:.1f} ms" for r in working if r is not best)
    if best is reference and any(r["ms_per_frame"] < best["ms_per_frame"] for r in same):
        others += f", not {MARGIN:.0%} faster"

    why = (f"{best['renderer']} renders {size} px frames in {best['ms_per_frame']:.1f} ms"
           + (f" ({others}; identical frames)" if others else "")
           + "".join(f"; {r['renderer']} renders different frames, not used" for r in working if r not in same))
    return {"results": results, "choice": best["renderer"], "why": why}


def choose_renderer(verbose: bool = True) -> str:
    """The backend to render with: ``MUJOCO_GL`` if set, else the measured fastest (cached per machine)."""
    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    key = _machine_key()
    try:
        cached = json.loads(CACHE.read_text())
        if cached.get("key") == key:
            return cached["choice"]
    except (OSError, ValueError):
        pass
    start = time.perf_counter()
    result = measure()
    try:
        CACHE.parent.mkdir(parents=True, exist_ok=True)
        tmp = CACHE.with_suffix(f".{os.getpid()}.tmp")   # atomic: pool workers may measure at the same time
        tmp.write_text(json.dumps({"key": key, **result}, indent=2))
        os.replace(tmp, CACHE)
    except OSError:
        pass
    if verbose:
        print(f"[jepa_envs] renderer: {result['choice']} ({result['why']}; measured in "
              f"{time.perf_counter() - start:.0f}s, cached in {CACHE}; set MUJOCO_GL to override)", file=sys.stderr)
    return result["choice"]


def use_renderer(verbose: bool = True) -> str:
    """Set ``MUJOCO_GL`` (and PyOpenGL's platform) for this process before MuJoCo is first imported."""
    global _chosen_by
    if not _chosen_by:
        _chosen_by = "you" if os.environ.get("MUJOCO_GL") else "measured"
    choice = choose_renderer(verbose)
    os.environ["MUJOCO_GL"] = choice
    if choice in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", choice)
    return choice


def bench_renderers(frames: int = 20, size: int = 84, threads: tuple[int, ...] | None = None,
                    progress: bool = False) -> list[dict]:
    """Print and return ms per ``size`` px frame for every backend and Mesa llvmpipe thread count, side by side
    in one run, with whether its frames equal the reference's and which backend this machine uses
    (``progress``: a bar of the probes on stderr)."""
    cores = os.cpu_count() or 1
    threads = threads or tuple(sorted({1, cores}))
    rows = []
    probes = [(name, t) for name in CANDIDATES for t in threads]
    for name, t in tqdm(probes, desc="renderers", unit="probe", disable=not progress):
        row = probe(name, frames, size, extra_env={"LP_NUM_THREADS": str(t)})
        rows.append({**row, "lp_num_threads": t})
    # today's default path: osmesa with llvmpipe's default thread count (one per core)
    reference = next((r for r in rows if r["renderer"] == REFERENCE and "error" not in r
                      and r["lp_num_threads"] == cores), None)
    base = reference["ms_per_frame"] if reference else None
    print(f"renderers: {frames} frames of {size} px, {rows[0].get('scene', 'MuJoCo scene')}; load "
          f"{os.getloadavg()[0]:.1f} on {cores} cores")
    print(f"{'backend':<10}{'LP_NUM_THREADS':>16}{'ms/frame':>10}{'vs osmesa':>11}  frames")
    for r in rows:
        if "error" in r:
            print(f"{r['renderer']:<10}{r['lp_num_threads']:>16}{'-':>10}{'-':>11}  does not work here: {r['error']}")
            continue
        same = "identical" if reference and r["digest"] == reference["digest"] else "DIFFERENT"
        ratio = f"{base / r['ms_per_frame']:.2f}x" if base else "-"
        print(f"{r['renderer']:<10}{r['lp_num_threads']:>16}{r['ms_per_frame']:>10.1f}{ratio:>11}  {same}")
    by_user = _chosen_by == "you" or (not _chosen_by and os.environ.get("MUJOCO_GL"))
    chosen = os.environ.get("MUJOCO_GL") if by_user else choose_renderer(verbose=False)
    print(f"in use: {chosen} ({'MUJOCO_GL set by you' if by_user else 'measured choice, cached in ' + str(CACHE)})")
    return rows
