"""The robot's loop, sustained: IMAGE in at a scanner's rate, TRANSFORM out, over loopback, for minutes.

    .venv/bin/python benchmarks/bench_igtl_loop.py [--minutes 10] [--rate 10] [--distinct 20]

A scanner-bridge stand-in (a TCP server in this process) sends pyigtl IMAGE
messages (256 x 256 int16, simulated slices of designs/neuro.yaml, Rician SNR
20, a spread of poses) on a fixed clock (``--rate`` Hz, not waiting for
replies) to the real ``chic-register track - --igtl-images HOST:PORT``,
started as its own process with verification on (the default). Every image
carries its own timestamp, which the tracker echoes in its replies, so each
TRANSFORM (or STATUS ``no_lock``) is paired with the image it answers.

Reports, from the bridge's side: latency IMAGE sent -> TRANSFORM ``CHIC``
received (median, p99, max; no-lock replies by their STATUS), images without
a reply (dropped), the tracker process's resident memory sampled over the run
(first minute, last minute, slope), its CPU time per image, and the load
average. Goals (issue "Real time"): median <= 15 ms, p99 <= 40 ms, no drops,
flat memory.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from chic_design.families import geometry_of
from chic_design.spec import load_spec
from chic_register.imaging.simulate import simulate_slice
from chic_register.io.igtl import read_message, slice_to_image_message
from chic_register.model.geometry import write_geometry

ROOT = Path(__file__).resolve().parents[1]
#: Replies are paired with images by the echoed timestamp, rounded to this (s): far below the send period.
TIMESTAMP_RESOLUTION_S = 1e-4
#: How long after the last image a reply may still come before the image counts as dropped (s).
GRACE_S = 5.0
#: Resident-memory sampling interval (s).
MEMORY_EVERY_S = 5.0


def rss_mb(pid: int) -> float:
    """Resident set size (MiB) of process ``pid`` (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process ``pid`` so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def simulated_slices(design: str, distinct: int):
    geom = geometry_of(load_spec(design))
    rng = np.random.default_rng(0)
    out = []
    for k in range(distinct):
        depth, tilt, az, tw = rng.uniform(15, 35), rng.uniform(0, 20), rng.uniform(-180, 180), rng.uniform(-180, 180)
        sim = simulate_slice(geom, depth, tilt, az, tw, noise="rician", snr=20.0, slice_thickness_mm=2.0, rng=k,
                             image_position=(-64.0, -64.0, 10.0))
        out.append(sim.slice)
    return geom, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="how long the bridge streams (default 10)")
    ap.add_argument("--rate", type=float, default=10.0, help="images per second (default 10)")
    ap.add_argument("--distinct", type=int, default=20, help="distinct simulated poses, cycled (default 20)")
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    args = ap.parse_args()

    geom, slices = simulated_slices(args.design, args.distinct)
    n_images = int(round(args.minutes * 60 * args.rate))
    period = 1.0 / args.rate
    work = Path(tempfile.mkdtemp(prefix="chic-igtl-loop-"))
    geometry_path = write_geometry(geom, work / "geometry.yaml")
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    exe = Path(sys.executable).parent / "chic-register"
    out_file = (work / "track.jsonl").open("w")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    tracker = subprocess.Popen([str(exe), "track", "-", "--geometry", str(geometry_path), "--igtl-images",
                                f"127.0.0.1:{port}", "--json"], stdout=out_file, stderr=subprocess.DEVNULL, env=env)
    listener.settimeout(120)
    conn, _ = listener.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    base = time.time()
    sent: dict[int, float] = {}
    replied: dict[int, tuple[float, str]] = {}
    memory: list[tuple[float, float]] = []
    done = threading.Event()

    def receive():
        while not done.is_set():
            try:
                m = read_message(conn, timeout_s=0.5)
            except socket.timeout:
                continue
            except OSError:
                return
            if m is None:
                return
            t = time.perf_counter()
            k = int(round((m.timestamp - base) / period))
            if m.message_type == "TRANSFORM" and m.device_name == "CHIC":
                replied.setdefault(k, (t, "ok"))
            elif m.message_type == "STATUS" and k not in replied:
                replied[k] = (t, "ok" if getattr(m, "code", 1) == 1 else "no_lock")

    receiver = threading.Thread(target=receive, daemon=True)
    receiver.start()
    cpu0 = cpu_s(tracker.pid)
    t_start = time.perf_counter()
    next_memory = t_start
    for k in range(n_images):
        msg = slice_to_image_message(slices[k % len(slices)], "MRI", timestamp=base + k * period).pack()
        due = t_start + k * period
        now = time.perf_counter()
        if now >= next_memory:
            memory.append((now - t_start, rss_mb(tracker.pid)))
            next_memory += MEMORY_EVERY_S
        if due > now:
            time.sleep(due - now)
        sent[k] = time.perf_counter()
        conn.sendall(msg)
    deadline = time.perf_counter() + GRACE_S
    while len(replied) < n_images and time.perf_counter() < deadline:
        time.sleep(0.05)
    memory.append((time.perf_counter() - t_start, rss_mb(tracker.pid)))
    cpu = cpu_s(tracker.pid) - cpu0
    done.set()
    conn.close()
    tracker.wait(30)
    out_file.close()
    listener.close()

    lat = np.array([1000.0 * (replied[k][0] - sent[k]) for k in sent if k in replied and replied[k][1] == "ok"])
    no_lock = sum(1 for k in sent if k in replied and replied[k][1] == "no_lock")
    dropped = sum(1 for k in sent if k not in replied)
    solve = [json.loads(line).get("solve_ms") for line in (work / "track.jsonl").read_text().splitlines()
             if line.startswith("{") and '"solve_ms"' in line]
    mem = np.array(memory)
    first = mem[mem[:, 0] <= 60.0, 1]
    last = mem[mem[:, 0] >= mem[-1, 0] - 60.0, 1]
    slope = np.polyfit(mem[:, 0] / 60.0, mem[:, 1], 1)[0] if len(mem) > 2 else float("nan")
    print(f"{n_images} IMAGE messages (256 x 256 int16) at {args.rate:g} Hz for {args.minutes:g} min over loopback "
          f"to chic-register track (verification on); {len(lat)} answered with a pose, {no_lock} no_lock, "
          f"{dropped} dropped")
    print(f"IMAGE sent -> TRANSFORM received: median {np.median(lat):.1f} ms, p99 {np.percentile(lat, 99):.1f} ms, "
          f"max {lat.max():.1f} ms (registration inside it: median {np.median(solve):.1f} ms)")
    print(f"tracker memory (RSS): first minute {first.mean():.1f} MiB, last minute {last.mean():.1f} MiB, "
          f"slope {slope:+.2f} MiB/min over {len(mem)} samples")
    print(f"tracker CPU time per image: {1000.0 * cpu / n_images:.1f} ms; load average {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
