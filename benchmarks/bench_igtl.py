"""Latency of the OpenIGTLink loop: IMAGE received -> TRANSFORM sent, 256 x 256 slices, on loopback.

    .venv/bin/python benchmarks/bench_igtl.py [--images 100] [--distinct 20] [--verify on|off]

A scanner bridge (a TCP server in this process, sending pyigtl IMAGE
messages, int16, LPS) streams simulated slices of designs/neuro.yaml (Rician
SNR 20, 2 mm slices, a spread of poses) to ``track_images`` (a thread, the
code behind ``chic-register track - --igtl-images HOST:PORT``), one image at a
time: it waits for the STATUS that ends each reply before sending the next.
Reports the tracker's own latency (last byte of the IMAGE read -> TRANSFORMs
handed to the socket; includes decoding, registration and packing), the
bridge's round trip (IMAGE sent -> STATUS received), the CPU time per image
of the whole process (``time.process_time``: steadier on a shared machine),
and the load average. ``--verify off`` registers without the solver's
pose verification against the image (``SolveOptions(verify=False)``), to
separate the loop's own cost from the solver's.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from chic_design.families import geometry_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.imaging.simulate import simulate_slice  # noqa: E402
from chic_register.io.igtl import read_message, slice_to_image_message  # noqa: E402
from chic_register.live.igtl_track import track_images  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=100, help="images streamed (default 100)")
    ap.add_argument("--distinct", type=int, default=20, help="distinct simulated poses, cycled (default 20)")
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    ap.add_argument("--verify", choices=("on", "off"), default="on",
                    help="the solver's verification of the pose against the image (default on, as chic-register)")
    args = ap.parse_args()
    from chic_register.options import SolveOptions

    options = SolveOptions(verify=args.verify == "on")

    geom = geometry_of(load_spec(args.design))
    rng = np.random.default_rng(0)
    msgs = []
    for k in range(args.distinct):
        depth, tilt, az, tw = rng.uniform(15, 35), rng.uniform(0, 20), rng.uniform(-180, 180), rng.uniform(-180, 180)
        sim = simulate_slice(geom, depth, tilt, az, tw, noise="rician", snr=20.0, slice_thickness_mm=2.0, rng=k,
                             image_position=(-64.0, -64.0, 10.0))
        msgs.append(slice_to_image_message(sim.slice, "MRI").pack())

    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    events = []
    tracker = threading.Thread(target=lambda: track_images(geom, connect=f"127.0.0.1:{port}", max_images=args.images,
                                                           timeout_s=600.0, on_event=events.append,
                                                           options=options), daemon=True)
    tracker.start()
    conn, _ = listener.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    round_trip = []
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for n in range(args.images):
        t0 = time.perf_counter()
        conn.sendall(msgs[n % len(msgs)])
        while True:
            m = read_message(conn, timeout_s=30.0)
            if m.message_type == "STATUS":
                break
        round_trip.append(1000.0 * (time.perf_counter() - t0))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    tracker.join(30)
    conn.close()
    listener.close()
    lat = np.array([e.latency_ms for e in events])
    solve = np.array([e.solve_ms for e in events])
    ok = sum(e.status == "ok" for e in events)
    print(f"{len(events)} images of 256x256 ({ok} ok, {len(events) - ok} no lock), {args.distinct} distinct poses, "
          f"verify {args.verify}")
    print(f"IMAGE received -> TRANSFORM sent: median {np.median(lat):.1f} ms, p95 {np.percentile(lat, 95):.1f} ms, "
          f"max {lat.max():.1f} ms (registration inside it: median {np.median(solve):.1f} ms; the loop's own "
          f"share: median {np.median(lat - solve):.2f} ms)")
    print(f"bridge round trip IMAGE sent -> STATUS received: median {np.median(round_trip):.1f} ms, "
          f"p95 {np.percentile(round_trip, 95):.1f} ms")
    print(f"CPU time of the process per image: {1000.0 * cpu / args.images:.1f} ms "
          f"(wall {1000.0 * wall / args.images:.1f} ms); load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
