"""Regenerate docs/benchmarks.md: run every benchmark and record each figure block with its provenance.

    .venv/bin/python benchmarks/report.py                  # every section (hours: the hunts are long)
    .venv/bin/python benchmarks/report.py --only solve hunt_series   # these sections; the others kept
    .venv/bin/python benchmarks/report.py --quick --only solve       # a smoke run of the script, to stdout
    .venv/bin/python benchmarks/report.py --list                     # sections and their commands

Each section of docs/benchmarks.md is one entry of :data:`SECTIONS`: a title, a few sentences on what
is measured (and the target, where there is one), and one or more commands. The script runs each
command as a subprocess (``bash -o pipefail -c``, from the repository root, this interpreter's
environment first on ``PATH``) and writes, for each: the exact command, the date, the machine (CPU
model, cores, memory), the load average before and after, the wall time and the CPU time of the run
(user + system of the command and every process it waited for: a benchmark's workers included), its
exit code, and its output (stdout and stderr). On this kind of shared 2-core machine the wall time
mostly measures the other jobs; the CPU time and the benchmarks' own CPU figures are the steadier ones.

The file keeps each section between ``<!-- section: NAME -->`` and ``<!-- /section: NAME -->``;
``--only`` replaces those sections and keeps every other one as it is. Anything after the line
``<!-- notes -->`` (hand-written remarks on the figures) is kept as well.

Placeholders in a command: ``{python}`` this interpreter, ``{tmp}`` a fresh temporary folder of the
section (removed afterwards), ``{geometry:NAME}`` the geometry file of ``designs/NAME.yaml``
(written there through the library, without the CAD build).

``--quick`` runs each section's small variant (a few cases or draws: seconds, not a measurement) and
prints the result to stdout unless ``--out`` is given: it tests the script, it does not replace figures.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "docs" / "benchmarks.md"
NOTES_MARKER = "<!-- notes -->"
_SECTION_RE = re.compile(r"<!-- section: (?P<name>[\w-]+) -->\n.*?<!-- /section: (?P=name) -->\n", re.S)

PY = "{python}"
ONE_CORE = "OMP_NUM_THREADS=1 taskset -c 1 "


@dataclass(frozen=True)
class Section:
    name: str
    title: str
    about: str
    commands: tuple[str, ...]
    quick: tuple[str, ...] = field(default=())

    def run_commands(self, quick: bool) -> tuple[str, ...]:
        return (self.quick or self.commands) if quick else self.commands


SECTIONS: tuple[Section, ...] = (
    Section("install", "Install and build on a fresh clone",
            "The README's first command on a fresh clone of the committed code, in a new virtual environment "
            "(pip's cache warm): install, then build `designs/neuro.yaml`.",
            ("git clone -q . {tmp}/chic && cd {tmp}/chic && python3 -m venv .venv && .venv/bin/pip install -q -e . "
             "&& .venv/bin/chic-design build designs/neuro.yaml",),
            ("git clone -q . {tmp}/chic && ls {tmp}/chic/designs",)),
    Section("ci", "The test suite on a fresh clone",
            "The README's second command, `bash .ci/run`, on a fresh clone of the committed code: both "
            "environments, the Debian tools, the lint steps and every test (the slow ones too).",
            ("git clone -q . {tmp}/chic && cd {tmp}/chic && bash .ci/run",),
            ("git clone -q . {tmp}/chic && bash -n {tmp}/chic/.ci/run && echo '.ci/run parses'",)),
    Section("build", "Full build of `neuro`",
            "A full `chic-design build designs/neuro.yaml`: cold (a fresh process, as a user runs it, imports "
            "included) and warm (in one process), median of the runs, with the time of each step. Target: < 10 s.",
            (f"{PY} benchmarks/bench_build.py --runs 3",), (f"{PY} benchmarks/bench_build.py --runs 1",)),
    Section("check", "`chic-design check`",
            "The feasibility checks of `designs/neuro.yaml`, in-process and as a fresh CLI process. Target: < 2 s.",
            (f"{PY} benchmarks/bench_check.py designs/neuro.yaml --runs 5",),
            (f"{PY} benchmarks/bench_check.py designs/neuro.yaml --runs 1",)),
    Section("solve", "Detection + pose on one core, verification off",
            "18 poses of `neuro` (256 x 256, 0.5 mm pixels, 2 mm slices, Rician SNR 20), each registered 20 "
            "times on one core without the pose verification: the fit alone. Target: median detect + pose "
            "<= 5 ms.",
            (f"{ONE_CORE}{PY} benchmarks/bench_solve.py --repeats 20 --efficiency-draws 0 --verify off",),
            (f"{ONE_CORE}{PY} benchmarks/bench_solve.py --repeats 1 --efficiency-draws 0 --verify off",)),
    Section("solve_verified", "Detection + pose with the default verification",
            "The same 18 slices with the solver's defaults: every pose proved against the pixels before `ok`. "
            "Near-normal single slices whose 3-sigma tilt exceeds the trust limit are refused.",
            (f"{ONE_CORE}{PY} benchmarks/bench_solve.py --repeats 10 --efficiency-draws 0",),
            (f"{ONE_CORE}{PY} benchmarks/bench_solve.py --repeats 1 --efficiency-draws 0",)),
    Section("startup", "One-shot `chic-register solve` start-up",
            "A fresh `chic-register solve` of one DICOM slice against a bare `python -c 'import numpy, pydicom'`. "
            "Target: <= 1.3x the bare imports. Then, alternated with them, the real clinical Z-frame scan "
            "(20 slices, thighs in view) and the masked one, each against the one-slice solve. Target: <= 1.5x.",
            (f"{PY} benchmarks/bench_startup.py --runs 30",
             f"{PY} benchmarks/bench_startup.py --runs 15 --volume tests/data/real/zframe-clinical-3t.nrrd --prior RAS",
             f"{PY} benchmarks/bench_startup.py --runs 15 --volume tests/data/real/zframe-masked-b.nrrd --prior RAS"),
            (f"{PY} benchmarks/bench_startup.py --runs 3",)),
    Section("igtl", "OpenIGTLink latency",
            "IMAGE received -> TRANSFORM sent, 256 x 256 int16 slices on loopback, 20 poses at tilt 0-20 deg, "
            "Rician SNR 20; with the default solver and with the verification off. Target: median < 30 ms.",
            (f"{PY} benchmarks/bench_igtl.py --images 100", f"{PY} benchmarks/bench_igtl.py --images 100 --verify off"),
            (f"{PY} benchmarks/bench_igtl.py --images 5 --distinct 5",)),
    Section("igtl_loop", "The robot's loop, sustained",
            "A scanner-bridge stand-in sends IMAGE messages (256 x 256 int16, `neuro`, Rician SNR 20) at 10 Hz over "
            "loopback for 10 minutes, on its own clock, to the real `chic-register track - --igtl-images` "
            "(verification on); latency IMAGE sent -> TRANSFORM received at the bridge, dropped images, the "
            "tracker's memory over the run. Goal: median <= 15 ms, p99 <= 40 ms, no drops, flat memory.",
            (f"{PY} benchmarks/bench_igtl_loop.py --minutes 10",), (f"{PY} benchmarks/bench_igtl_loop.py --minutes 0.1",)),
    Section("volume", "Whole volumes without `--slices`",
            "60-slice volumes of `neuro` and of the z001 Z-frame: every native slice tried, the ones that lock "
            "registered jointly.",
            (f"{ONE_CORE}{PY} benchmarks/bench_volume.py",),
            (f"{ONE_CORE}{PY} benchmarks/bench_volume.py --repeats 1",)),
    Section("efficiency", "Efficiency against the Cramér-Rao bound",
            "RMS error over noise draws divided by the Cramér-Rao bound of the same protocol (`neuro`, 2 mm slices, "
            "0.5 mm pixels, Rician noise) for the image normal, twist, depth and the TRE at the body centre, on the "
            "paper's 18 study poses and a grid of tilts 0-45 deg x depths 10-40 mm; 100 draws per pose, up to 300 "
            "while a ratio's 95 % interval contains 1.15. Target: <= 1.15 at every pose.",
            tuple(f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_accuracy.py --crlb --draws 100 --draws-max 300 "
                  f"--snr {snr} --poses study grid" for snr in (10, 20, 50)),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_accuracy.py --crlb --draws 3 --snr 20 --poses study",)),
    Section("efficiency_study", "Efficiency: the 20-draw study check",
            "The paper's 18 study poses, 20 draws each at Rician SNR 20: a quick check of the same ratios "
            "(each good to about +-16 %).",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_accuracy.py --crlb --draws 20 --snr 20 --poses study",),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_accuracy.py --crlb --draws 2 --snr 20 --poses study",)),
    Section("bias", "Noise-free bias",
            "Noise-free slices of `neuro` at tilts 0-60 deg: every error is a bias of the model or the detector. "
            "With the solver's defaults, and with the template accuracy mode (`--centroid-model on`).",
            (f"{PY} benchmarks/bench_bias.py", f"{PY} benchmarks/bench_bias.py --centroid-model on")),
    Section("paper", "Accuracy against the paper's simulation study",
            "The paper's protocol (256 x 256, 0.5 mm pixels; 18 cases) with uniform white noise +-a of the fluid "
            "signal and Rician noise, 20 draws per case; maximum and SD of each error beside the paper's. "
            "Target: 3x better than the paper's maximum.",
            (f"{PY} benchmarks/bench_accuracy.py --draws 20 --snr 20 50",),
            (f"{PY} benchmarks/bench_accuracy.py --draws 1 --levels 0.025",)),
    Section("multislice", "Multi-slice precision",
            "`neuro`, parallel 2 mm slices at 20/25/30 mm, tilt 10 deg, Rician SNR 10, 200 draws: the SD of the "
            "middle slice's pose from 1, 2 and 3 slices registered jointly.",
            (f"{PY} benchmarks/bench_multislice.py --draws 200 --snr 10",),
            (f"{PY} benchmarks/bench_multislice.py --draws 3 --snr 10",)),
    Section("uncertainty", "Calibration of every pose's covariance",
            "Squared Mahalanobis length of the pose error under the reported covariance (6 when calibrated) and "
            "predicted over measured TRE (1 when calibrated), `neuro` and the z001 Z-frame, four poses x 50 "
            "draws per seed, Rician SNR 20.",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_uncertainty.py --draws 50 --seeds 21 5 11",),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_uncertainty.py --draws 2 --seeds 21",)),
    Section("independent", "Calibration and efficiency on images the solver did not draw",
            "`neuro` slices rendered from the printed body's mesh through k-space (`chic_register.studies.kspace`: "
            "the channels' fluid in a 2 mm sinc-pulse slab, the cropped DFT of the fine occupancy, 256 x 256 at "
            "0.5 mm, Rician noise), eight poses (the calibration study's four and tilts 0-45 deg) x 50 draws at "
            "SNR 10, 20, 50, the default solver: squared Mahalanobis length (6 when calibrated), predicted over "
            "measured TRE (1) and RMS error over the CRLB of the solver's own image model (1 when efficient); "
            "then the same with a Hamming k-space filter (wider blobs than the solver's model; noise still white).",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_independent.py --draws 50",
             f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_independent.py --draws 50 --filter hamming"),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_independent.py --quick",)),
    Section("nlocalizer", "The Leksell G localizer box: simulated CT and MR, and real slices",
            "`designs/leksell-g-ct.yaml` and `leksell-g-mr.yaml` against their truth: single CT slices (512 x 512, "
            "0.6 mm, plates, a skull on every other) and MR slices (Rician SNR 20) tilted about F's x and y, the "
            "same axial, four parallel axial CT slices, and 24-slice MR volumes whole and as two halves; TRE at the "
            "frame centre (Leksell (100, 100, 100)) beside the pose's own predicted TRE. Target: every tilted "
            "slice within the check's tilt limit (26 deg) locks within 0.3 mm, an axial slice is refused (two "
            "plates facing along x fix the turn about x only to second order), halves agree within their "
            "uncertainty. Then the five real slices of `tests/data/real/leksell`.",
            (f"{PY} benchmarks/bench_nlocalizer.py --seeds 6",), (f"{PY} benchmarks/bench_nlocalizer.py --seeds 1",)),
    Section("hunt", "False-lock hunt",
            "5000 random slices of `neuro` and `needle-guide` over and beyond the usable envelope (depth -15 % to "
            "115 %, tilt 0-80 deg, random pixel size, thickness, field of view and SNR), each with one damage kind, "
            "solved as `chic-register solve` does. A false lock is `ok` more than 0.5 mm (frame centre) or 0.5 deg "
            "from the truth. Target: no false lock; as large a share of the in-envelope slices locked as possible. "
            "The second run solves as `--scale-sd 0.2` does: what an uncalibrated print and scanner cost single "
            "slices when their scale's doubt is held in the trust test.",
            (f"{PY} benchmarks/hunt.py --cases 5000 --seed 0 --workers 2",
             f"{PY} benchmarks/hunt.py --cases 5000 --seed 0 --workers 2 --scale-sd 0.2"),
            (f"{PY} benchmarks/hunt.py --cases 50 --seed 0 --workers 2",)),
    Section("hunt_seeds", "False-lock hunt, other seeds",
            "The same hunt on five other seeds.",
            tuple(f"{PY} benchmarks/hunt.py --cases 5000 --seed {s} --workers 2" for s in range(1, 6)),
            (f"{PY} benchmarks/hunt.py --cases 20 --seed 1 --workers 2",)),
    Section("hunt_wide", "False-lock hunt with wide blobs",
            "The hunt with every blob drawn 1.1-1.5x and 1-2.5x its channel's width (point spread, partial volume).",
            (f"{PY} benchmarks/hunt.py --cases 1000 --seed 0 --workers 2 --blob-width 1.1 1.5",
             f"{PY} benchmarks/hunt.py --cases 2000 --seed 0 --workers 2 --blob-width 1 2.5"),
            (f"{PY} benchmarks/hunt.py --cases 20 --seed 0 --workers 2 --blob-width 1 2.5",)),
    Section("hunt_series", "Series hunt",
            "300 series of 2-4 parallel slices of `neuro`, the needle guide and the optimiser's slim needle guide, "
            "depth -10 % to 110 %, tilt 0-60 deg, SNR 8-40, registered as one series.",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/hunt_series.py --cases 300 --seed 11",),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/hunt_series.py --cases 5 --seed 11",)),
    Section("hunt_volume", "Volume hunt (wide blobs)",
            "128 x 128 x 40 volumes of both designs at random poses (tilt 0-30 deg, Rician SNR 12-30) with blobs "
            "1.5-2.5x and 1.1-1.7x the channels' width, registered whole.",
            (f"{PY} benchmarks/hunt_volume.py --cases 30 --seed 3",
             f"{PY} benchmarks/hunt_volume.py --cases 30 --seed 5 --blob-width 1.1 1.7"),
            (f"{PY} benchmarks/hunt_volume.py --cases 1 --seed 3",)),
    Section("hunt_unlisted", "Damage the hunt does not draw",
            "The hunt's noisy slices with one of twenty other kinds of damage (specks, motion blur, Gibbs ringing, "
            "wrap, quantisation, a 2x zoom, NaN pixels, offsets, k-space spikes, partial Fourier, resampled "
            "rotations, sub-pixel shifts, 8-bit clipping, inverted contrast, signed phase-ramped data, "
            "susceptibility voids, Nyquist ghosts, radial warps, JPEG blocks).",
            (f"{PY} benchmarks/hunt_unlisted.py --cases 2000 --seed 1",
             f"{PY} benchmarks/hunt_unlisted.py --cases 1000 --seed 2",
             f"{PY} benchmarks/hunt_unlisted.py --cases 1000 --seed 3",
             f"{PY} benchmarks/hunt_unlisted.py --cases 1000 --seed 7"),
            (f"{PY} benchmarks/hunt_unlisted.py --cases 20 --seed 7",)),
    Section("hunt_distortion", "False-lock hunt under scanner effects",
            "The main hunt's cases drawn as real scanners show them (a scale of 0.1-1 % per image axis, a gradient "
            "non-linearity of 0-4 mm at 100 mm from an isocentre within 20 mm of the image centre, shading up to "
            "60 %, up to six tissue regions), "
            "judged against the pose the distorted image shows. Target: 0 false locks.",
            (f"{PY} benchmarks/hunt_distortion.py --cases 2000 --seed 0",
             f"{PY} benchmarks/hunt_distortion.py --cases 2000 --seed 1"),
            (f"{PY} benchmarks/hunt_distortion.py --cases 10 --seed 0",)),
    Section("hunt_print", "What the print and the geometry file must get right",
            "The hunt's noisy slices changed as a print or a stale geometry file would change them; the scale runs "
            "also as `--scale-sd` solves them (the print's scale held in the single slice's covariance).",
            tuple(f"{PY} benchmarks/hunt_print.py {args}" for args in (
                "--kind bubble --cases 1200", "--kind water_bath --cases 600", "--kind dim_tube --cases 600",
                "--kind scale --amount 0.001 --cases 1000", "--kind scale --cases 1000",
                "--kind scale --amount 0.004 --cases 1000", "--kind scale --amount 0.001 --cases 1000 --scale-sd 0.2",
                "--kind scale --cases 1000 --scale-sd 0.2", "--kind scale --amount 0.004 --cases 1000 --scale-sd 0.4",
                "--kind helix_offset --seed 3 --cases 300",
                "--kind helix_offset --amount 2 --seed 3 --cases 300", "--kind other_design --cases 600")),
            (f"{PY} benchmarks/hunt_print.py --kind bubble --cases 10",)),
    Section("stress_zframe", "Z-frame volumes that look like real scans",
            "40 volumes of the z001 Z-frame with blobs 1.5-2.5x, Rician SNR 8-30, 1-3 mm slices, tilts 0-28 deg and "
            "at random unequal rods, bubbles, bias field and coil fall-off, slice gaps, empty slices, a frame cut "
            "off, tissue, a grid plate, a phantom, non-square pixels, oblique storage, int16; written as NRRD, "
            "NIfTI or a DICOM series, solved through the CLI with a prior turned up to 30 deg and without.",
            (f"OMP_NUM_THREADS=1 PYTHONPATH=. {PY} benchmarks/stress_zframe_volume.py --cases 40 --seed 0 "
             "--geometry {geometry:zframe}",),
            (f"OMP_NUM_THREADS=1 PYTHONPATH=. {PY} benchmarks/stress_zframe_volume.py --cases 2 --seed 0 "
             "--geometry {geometry:zframe}",)),
    Section("blurred_calibration", "Single slices with wide blobs: is their covariance calibrated?",
            "Single simulated slices with blobs 1.5-2.5x the channels' width (Rician SNR 15-30, tilts 10-30 deg), "
            "registered with the defaults: per kind of measurement, the squared Mahalanobis length of the pose "
            "error under the reported covariance (6 when calibrated) and the rotation error.",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_blurred_calibration.py --design zframe --cases 80",
             f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_blurred_calibration.py --design needle-guide --cases 80",
             f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_blurred_calibration.py --design neuro --cases 80"),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_blurred_calibration.py --design zframe --cases 4",)),
    Section("real_variants", "The real Z-frame scans, changed as scanners and exports change them",
            "The two real Z-frame volumes of tests/data/real, each registered as it is and then stored otherwise "
            "(slice order, flipped or swapped axes, an oblique or moved frame: the pose must follow exactly), "
            "cropped or padded, with their intensities rescaled, offset, clipped or quantised to 8 bits, thinned to "
            "every second slice, binned 2 x 2, noisier, or shaded across the field of view. An ok more than 0.5 mm "
            "or 0.5 deg from the plain scan's pose is marked FAR.",
            (f"PYTHONPATH=. {PY} benchmarks/bench_real_variants.py",),
            (f"PYTHONPATH=. {PY} benchmarks/bench_real_variants.py --scan tests/data/real/zframe-masked-b.nrrd",)),
    Section("zframe_peer", "Z-frame volumes against 3D Slicer's ZFrameRegistration",
            "40 simulated z001 volumes drawn as real scans (0.6-0.8 mm pixels, 2-3 mm slices, SNR 10-30, blobs "
            "1.5-2.5x, tilts 0-5 deg, rod ends 0.1-0.3 mm off, a scanner's scale of 0.2-1 % in-plane and 1-3 % across "
            "the slices) registered by the solver (with the prior) and by ZFrameRegistration's algorithm "
            "(`benchmarks/peers/zframe_susil.py`, Susil et al. 1999), errors against the frame as the image shows it; "
            "then both on the real scans.",
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_zframe_peer.py --cases 40 --seed 0",),
            (f"OMP_NUM_THREADS=1 {PY} benchmarks/bench_zframe_peer.py --cases 2 --seed 0",)),
    Section("optimize_speed", "`chic-design optimize`: candidates per second",
            "The same seeded search (neuro requirements, 48 candidates, nothing cached) serially, on a local pool "
            "of 2 workers and on a 2-worker Dask LocalCluster; all must find the same Pareto set.",
            (f"{PY} benchmarks/bench_optimize.py --trials 48",), (f"{PY} benchmarks/bench_optimize.py --trials 4",)),
    Section("optimize", "`chic-design optimize` end to end",
            "The default searches of both requirement files (240 candidates, 2 local workers), with the "
            "confirmation by simulation.",
            ("chic-design optimize designs/requirements/neuro.yaml --quiet --out {tmp}/neuro",
             "chic-design optimize designs/requirements/needle-guide.yaml --quiet --out {tmp}/needle-guide"),
            ("chic-design optimize designs/requirements/needle-guide.yaml --trials 4 --quiet --out {tmp}/ng",)),
    Section("calibrate_trust", "The optimiser's solver-trust factor",
            "The solver's own 1-sigma estimate over the Cramér-Rao bound (`neuro` at 0.5 mm / 2 mm and a slim "
            "needle guide at 0.3 mm / 1.5 mm, 1 and 3 slices, SNR 20): the factor the optimiser's trust test uses.",
            (f"{PY} benchmarks/calibrate_trust.py --draws 6 --seed 0",),
            (f"{PY} benchmarks/calibrate_trust.py --draws 1 --seed 0 --n-slices 1",)),
    Section("reslice", "Reformatted volume (the paper's Table II protocol)",
            "A 128 x 128 x 120 volume at 0.5 mm, Rician SNR 20, resliced with a 15 deg tilt at 1 mm steps.",
            ("chic-register simulate --geometry {geometry:neuro} --depth 25 --tilt 3 --azimuth 20 --twist 30 "
             "--volume-shape 128 128 120 --voxel-size 0.5 --noise rician --snr 20 --seed 1 --out {tmp}/hires.nii.gz"
             " && chic-register reslice {tmp}/hires.nii.gz --geometry {geometry:neuro} "
             "--reference {tmp}/hires.nii.gz.truth.json --size 128 --depth-step 1",)),
)
BY_NAME = {s.name: s for s in SECTIONS}


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text())[1])
        mem = f", {kb / 2**20:.0f} GiB"
    except (OSError, TypeError):
        pass
    system = f"{platform.system()} {platform.release()}, Python {platform.python_version()}"
    return f"{cpu}, {os.cpu_count()} cores{mem}; {system}"


def _load() -> str:
    try:
        return " / ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def _display(cmd: str) -> str:
    """The command as a user types it from the repository root."""
    py = Path(sys.executable).absolute()
    shown = os.path.relpath(py, ROOT) if py.is_relative_to(ROOT) else str(py)
    cmd = cmd.replace("{python}", shown).replace("{tmp}", "TMP")
    return re.sub(r"\{geometry:([\w.-]+)\}", r"exports/\1/geometry.yaml", cmd)


class _Geometries:
    def __init__(self, folder: Path):
        self.folder, self.files = folder, {}

    def __call__(self, name: str) -> str:
        if name not in self.files:
            from chic_design.spec import load_spec
            from chic_register.model.geometry import write_geometry

            spec = load_spec(ROOT / "designs" / f"{name}.yaml")
            source = {"spec": f"designs/{name}.yaml"}
            from chic_design.families import geometry_of

            geometry = geometry_of(spec, source)
            out = self.folder / f"{name}-geometry.yaml"
            write_geometry(geometry, out)
            self.files[name] = str(out)
        return self.files[name]


def _expand(cmd: str, tmp: Path, geometries: _Geometries) -> str:
    cmd = cmd.replace("{python}", sys.executable).replace("{tmp}", str(tmp))
    return re.sub(r"\{geometry:([\w.-]+)\}", lambda m: geometries(m[1]), cmd)


def run_command(cmd: str, tmp: Path, geometries: _Geometries, timeout: float | None) -> dict:
    env = dict(os.environ, PYTHONUNBUFFERED="1", MPLBACKEND="Agg",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    expanded = _expand(cmd, tmp, geometries)
    load_before = _load()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    try:
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", expanded], cwd=ROOT, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout)
        output, code = proc.stdout, proc.returncode
    except subprocess.TimeoutExpired as e:
        output = (e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        code = f"timeout after {timeout:.0f} s"
    wall = time.monotonic() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    output = output.replace(str(tmp), "TMP").replace(str(ROOT) + "/", "")
    # progress bars rewrite their line with \r: keep what the terminal would show last
    output = "\n".join(line.rsplit("\r", 1)[-1] for line in output.splitlines())
    return {"command": _display(cmd), "date": _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
            "load_before": load_before, "load_after": _load(), "wall_s": wall, "cpu_s": cpu, "exit": code,
            "output": output.rstrip()}


def _fence(text: str) -> str:
    ticks = "```"
    while ticks in text:
        ticks += "`"
    return f"{ticks}text\n{text}\n{ticks}"


def render_section(section: Section, runs: list[dict], quick: bool, host: str) -> str:
    out = [f"<!-- section: {section.name} -->", f"## {section.title}", "", section.about, ""]
    if quick:
        out += ["*Quick run (`--quick`): a smoke test of the script, not a measurement.*", ""]
    for r in runs:
        out += [f"Command: `{r['command']}`", "",
                f"- date: {r['date']}; machine: {host}",
                f"- load average (1 / 5 / 15 min): {r['load_before']} before, {r['load_after']} after",
                f"- wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s (user + system, with its workers); "
                f"exit {r['exit']}", "", _fence(r["output"] or "(no output)"), ""]
    out.append(f"<!-- /section: {section.name} -->")
    return "\n".join(out) + "\n"


HEADER = """# CHIC benchmarks

Measured figures of `chic-design` and `chic-register`, with the command that produced each, when, on
which machine and at what load. This file is written by `benchmarks/report.py`:

```sh
.venv/bin/python benchmarks/report.py --list                 # the sections and their commands
.venv/bin/python benchmarks/report.py --only solve startup   # regenerate some sections, keep the others
.venv/bin/python benchmarks/report.py                        # every section (hours: the hunts are long)
```

Run the benchmarks on an otherwise idle machine: wall times on a shared one mostly measure the other
jobs (the load average is recorded before and after each run for that reason; the CPU times are the
steadier figures). In the commands, `TMP` is a scratch folder of the run and
`exports/NAME/geometry.yaml` the geometry of `designs/NAME.yaml`, written for the run without the CAD
build. Sections whose provenance says *recorded* hold figures measured before this script existed,
with the command and the date they were measured with; regenerate them to replace them.

"""


def split_file(text: str) -> tuple[dict[str, str], str]:
    sections = {m["name"]: m[0] for m in _SECTION_RE.finditer(text)}
    notes = ""
    if NOTES_MARKER in text:
        notes = text[text.index(NOTES_MARKER):]
    return sections, notes


def assemble(sections: dict[str, str], notes: str) -> str:
    parts = [HEADER]
    for s in SECTIONS:
        if s.name in sections:
            parts.append(sections[s.name] + "\n")
    extra = [name for name in sections if name not in BY_NAME]
    for name in extra:  # sections of names the script no longer has: kept, at the end
        parts.append(sections[name] + "\n")
    if notes:
        parts.append(notes.rstrip() + "\n")
    return "".join(parts).rstrip() + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="+", metavar="NAME", help="regenerate these sections, keep the others")
    ap.add_argument("--quick", action="store_true", help="small variants: test the script (output to stdout)")
    ap.add_argument("--out", default=None,
                    help=f"file to write (default: {DEFAULT_OUT.relative_to(ROOT)}; with --quick: stdout, '-')")
    ap.add_argument("--timeout", type=float, default=None, help="seconds allowed per command (default: none)")
    ap.add_argument("--list", action="store_true", help="list the sections and their commands, run nothing")
    args = ap.parse_args(argv)

    if args.list:
        for s in SECTIONS:
            print(f"{s.name}: {s.title}")
            for c in s.run_commands(args.quick):
                print(f"    {_display(c)}")
        return 0
    unknown = [n for n in (args.only or []) if n not in BY_NAME]
    if unknown:
        print(f"report.py: unknown section(s) {', '.join(unknown)}; known: {', '.join(BY_NAME)}", file=sys.stderr)
        return 2
    chosen = [BY_NAME[n] for n in args.only] if args.only else list(SECTIONS)
    out = args.out or ("-" if args.quick else str(DEFAULT_OUT))
    out_path = None if out == "-" else Path(out)

    existing = out_path.read_text(encoding="utf-8") if out_path is not None and out_path.exists() else ""
    sections, notes = split_file(existing)
    host = machine()
    failed = []
    with tempfile.TemporaryDirectory(prefix="chic-report-") as scratch:
        geometries = _Geometries(Path(scratch))
        for s in chosen:
            runs = []
            for cmd in s.run_commands(args.quick):
                tmp = Path(tempfile.mkdtemp(prefix=f"{s.name}-", dir=scratch))
                print(f"report.py: [{s.name}] {_display(cmd)}", file=sys.stderr, flush=True)
                r = run_command(cmd, tmp, geometries, args.timeout)
                print(f"report.py: [{s.name}] exit {r['exit']}, wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s",
                      file=sys.stderr, flush=True)
                if r["exit"] != 0:
                    failed.append(f"{s.name}: {r['command']} (exit {r['exit']})")
                runs.append(r)
                shutil.rmtree(tmp, ignore_errors=True)
            sections[s.name] = render_section(s, runs, args.quick, host)
            if out_path is not None:  # written after every section: a long run interrupted keeps what it did
                out_path.write_text(assemble(sections, notes), encoding="utf-8")
    if out_path is None:
        sys.stdout.write("".join(sections[s.name] + "\n" for s in chosen))
    else:
        print(f"wrote {out_path}", file=sys.stderr)
    for f in failed:
        print(f"report.py: non-zero exit: {f}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BrokenPipeError:  # `report.py --list | head`
        sys.exit(141)
