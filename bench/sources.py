#!/usr/bin/env python3
"""Driver benchmark: frame rate, capture-to-delivery latency and timestamp regularity, single thread.

    .venv/bin/python bench/sources.py [--frames 90] [--fps 30] [--no-aravis]

Cases, each next to a reference that reads the same data without edgecal in the same run:

* replay, as fast as possible: edgecal's ``replay:`` of a rendered PNG sequence vs a bare
  ``cv2.imdecode`` loop over the same files (frames per second; the ratio is edgecal's overhead);
* replay paced in real time at --fps: regularity of the delivery times (median interval vs the nominal
  period, p99 jitter = 99th percentile of |interval - period|) and latency from the frame's due time;
* MCAP, as fast as possible: edgecal's ``mcap:`` source over the same frames written as ROS 2
  sensor_msgs/msg/Image (mono8) and as CompressedImage (JPEG), vs a bare loop of the ``mcap`` reader
  with mcap-ros2-support's decoder and the same pixel conversion (np.frombuffer / cv2.imdecode);
* the Aravis fake GigE Vision camera (arv-fake-gv-camera-0.8 on 127.0.0.1, 512x512 Mono8) at --fps:
  edgecal's AravisSource vs a bare libaravis pop loop. Latency is wall clock at delivery minus the
  camera's timestamp: the fake camera stamps frames with the host's wall clock, so the difference is
  the real capture-to-delivery time (network stack, reassembly, conversion). Regularity is measured on
  the frames' ``stamp_ns`` (the device clock mapped to CLOCK_MONOTONIC) after the mapping's 30-frame
  warm-up, next to the bare device timestamps of the same frames' reference run.
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import fcntl  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from edgecal.drivers import open_source  # noqa: E402
from edgecal.runtime import tune_allocator  # noqa: E402

LOCK = Path("/tmp/edgecal-arv-fake-gv.lock")   # shared with the tests: one fake camera at a time


def regularity(stamps_ns: list[int], period_ns: float) -> dict:
    """Median interval (ms), its deviation from the nominal period (%), and p99 |interval - period| (ms)."""
    iv = np.diff(np.asarray(stamps_ns, dtype=np.int64)).astype(np.float64)
    med = float(np.median(iv))
    return {"median_ms": med / 1e6, "off_pct": 100.0 * abs(med - period_ns) / period_ns,
            "p99_jitter_ms": float(np.percentile(np.abs(iv - period_ns), 99)) / 1e6}


def render_sequence(folder: Path, n: int) -> list[Path]:
    """n 640x480 grey PNG frames of a moving chessboard with noise."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:480, 0:640]
    files = []
    for i in range(n):
        img = ((((x + 3 * i) // 40 + y // 40) % 2) * 180 + 30 + rng.integers(0, 20, (480, 640))).astype(np.uint8)
        p = folder / f"{i:05d}.png"
        cv2.imwrite(str(p), img)
        files.append(p)
    return files


def bench_replay_fast(folder: Path, files: list[Path]) -> None:
    t0 = time.perf_counter()
    for p in files:
        cv2.imdecode(np.fromfile(str(p), np.uint8), cv2.IMREAD_UNCHANGED)
    ref = len(files) / (time.perf_counter() - t0)
    lat = []
    t0 = time.perf_counter()
    with open_source(f"replay:{folder}?pace=fast") as src:
        n = 0
        for f in src:
            lat.append(time.monotonic_ns() - f.recv_ns)
            n += 1
    ours = n / (time.perf_counter() - t0)
    print(f"replay fast      edgecal {ours:7.1f} fps   cv2.imdecode loop {ref:7.1f} fps   ratio {ours / ref:.2f}   "
          f"delivery latency median {np.median(lat) / 1e3:.1f} us")


def bench_replay_paced(folder: Path, fps: float, n: int) -> None:
    period = 1e9 / fps
    with open_source(f"replay:{folder}?fps={fps:g}") as src:
        t_start = None
        recv, late = [], []
        for _ in range(n):
            f = src.read()
            if f is None:
                break
            now = time.monotonic_ns()
            if t_start is None:
                t_start = now - f.stamp_ns
            recv.append(now)
            late.append(now - (t_start + f.stamp_ns))
    r = regularity(recv, period)
    print(f"replay {fps:g} fps   delivery interval median {r['median_ms']:.3f} ms ({r['off_pct']:.2f} % off "
          f"{period / 1e6:.3f}), p99 jitter {r['p99_jitter_ms']:.3f} ms, lateness median "
          f"{np.median(late) / 1e3:.1f} us p99 {np.percentile(late, 99) / 1e3:.1f} us")


def _raw_aravis(n: int, fps: float) -> tuple[float, list[int], list[int]]:
    """A bare libaravis loop: fps, wall-clock latencies (ns), device timestamps."""
    from edgecal.drivers.aravis import load_aravis
    Aravis = load_aravis()
    cam = Aravis.Camera.new("127.0.0.1")
    cam.set_frame_rate(fps)
    stream = cam.create_stream(None, None)
    for _ in range(4):
        stream.push_buffer(Aravis.Buffer.new_allocate(cam.get_payload()))
    cam.start_acquisition()
    lat, stamps = [], []
    buf = stream.timeout_pop_buffer(2_000_000)   # first frame: start timing here
    stream.push_buffer(buf)
    t0 = time.perf_counter()
    got = 0
    while got < n:
        buf = stream.timeout_pop_buffer(2_000_000)
        if buf is None:
            break
        if buf.get_status() == Aravis.BufferStatus.SUCCESS:
            np.frombuffer(buf.get_data(), np.uint8).reshape(buf.get_image_height(), buf.get_image_width()).copy()
            lat.append(time.time_ns() - buf.get_timestamp())
            stamps.append(buf.get_timestamp())
            got += 1
        stream.push_buffer(buf)
    rate = got / (time.perf_counter() - t0)
    cam.stop_acquisition()
    del stream, cam
    return rate, lat, stamps


def bench_aravis(n: int, fps: float) -> None:
    if shutil.which("arv-fake-gv-camera-0.8") is None:
        print("aravis           skipped: arv-fake-gv-camera-0.8 not installed (Debian aravis-tools)")
        return
    period = 1e9 / fps
    with open(LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        proc = subprocess.Popen(["arv-fake-gv-camera-0.8", "-i", "127.0.0.1"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            time.sleep(0.5)
            ref_rate, ref_lat, ref_stamps = _raw_aravis(n, fps)
            lat, stamps, recv, device = [], [], [], []
            with open_source(f"aravis:127.0.0.1?fps={fps:g}&timeout_s=2") as src:
                src.read()
                t0 = time.perf_counter()
                for _ in range(n):
                    f = src.read()
                    lat.append(time.time_ns() - src.last_device_ns)
                    stamps.append(f.stamp_ns)
                    recv.append(f.recv_ns)
                    device.append(src.last_device_ns)
                rate = n / (time.perf_counter() - t0)
                dropped = src.dropped
        finally:
            proc.kill()
            proc.wait()
    # The clock mapping settles during its first 30 frames (docs/drivers.md); a live loop runs for hours.
    r = regularity(stamps[30:], period)
    rr = regularity(ref_stamps[30:], period)
    print(f"aravis fake {fps:g} fps  edgecal {rate:6.2f} fps (bare libaravis {ref_rate:6.2f}, ratio "
          f"{rate / ref_rate:.3f}), dropped {dropped}")
    print(f"  capture-to-delivery latency median {np.median(lat) / 1e6:.3f} ms p99 "
          f"{np.percentile(lat, 99) / 1e6:.3f} ms (bare libaravis median {np.median(ref_lat) / 1e6:.3f} ms, "
          f"ratio {np.median(lat) / np.median(ref_lat):.2f})")
    print(f"  stamp_ns interval median {r['median_ms']:.3f} ms ({r['off_pct']:.2f} % off {period / 1e6:.3f}), "
          f"p99 jitter {r['p99_jitter_ms']:.3f} ms (bare device stamps: median {rr['median_ms']:.3f} ms, "
          f"p99 jitter {rr['p99_jitter_ms']:.3f} ms)")
    added = np.abs(np.diff(np.asarray(stamps[30:])) - np.diff(np.asarray(device[30:])))
    print(f"  jitter added by the clock mapping (|interval of stamp_ns - interval of the device's stamps|): "
          f"p99 {np.percentile(added, 99) / 1e3:.1f} us, max {added.max() / 1e3:.1f} us")
    mapped_minus_recv = np.asarray(recv) - np.asarray(stamps)
    print(f"  recv_ns - stamp_ns median {np.median(mapped_minus_recv) / 1e6:.3f} ms "
          "(the mapped clock sits at the fastest frame's transport delay)")


def write_mcap_sequence(path: Path, files: list[Path], fmt: str) -> None:
    """The PNG sequence as an MCAP file of Image (``fmt`` raw) or CompressedImage (jpeg) messages on /cam."""
    from edgecal.mcap_writer import McapLogWriter
    from edgecal.ros_messages import compressed_image_message, image_message
    with McapLogWriter(path, force=True) as w:
        for i, p in enumerate(files):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            stamp = 10**18 + i * 33_333_333
            msg = image_message(img, stamp, "cam") if fmt == "raw" else compressed_image_message(img, stamp, "cam")
            w.write("/cam", msg, stamp)


def _bare_mcap(path: Path) -> int:
    """Frames of /cam decoded by the mcap libraries alone, pixels made an array as edgecal does."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    n = 0
    with path.open("rb") as f:
        for _, _, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/cam"]):
            if hasattr(msg, "encoding"):
                np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)[:, :msg.width].copy()
            else:
                cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
            n += 1
    return n


def bench_mcap(tmp: Path, files: list[Path], repeat: int = 3) -> None:
    """edgecal's mcap: source vs the bare mcap reader loop, raw and JPEG, medians of ``repeat`` runs each."""
    for fmt in ("raw", "jpeg"):
        path = tmp / f"seq-{fmt}.mcap"
        write_mcap_sequence(path, files, fmt)
        ours, ref = [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            n_ref = _bare_mcap(path)
            ref.append(n_ref / (time.perf_counter() - t0))
            t0 = time.perf_counter()
            with open_source(f"mcap:{path}?topic=/cam&pace=fast") as src:
                n = sum(1 for _ in src)
            ours.append(n / (time.perf_counter() - t0))
        assert n == n_ref == len(files)
        o, r = float(np.median(ours)), float(np.median(ref))
        print(f"mcap {fmt:4s}        edgecal {o:7.1f} fps   bare mcap reader loop {r:7.1f} fps   ratio {o / r:.2f}   "
              f"({path.stat().st_size / len(files) / 1024:.0f} KiB per frame)")


def main() -> None:
    """Run every case and print one block each."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=90, help="frames per case (default 90)")
    ap.add_argument("--fps", type=float, default=30.0, help="nominal rate for the paced cases (default 30)")
    ap.add_argument("--no-aravis", action="store_true", help="skip the fake-camera cases")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "seq"
        files = render_sequence(folder, args.frames)
        bench_replay_fast(folder, files)
        bench_replay_paced(folder, args.fps, args.frames)
        bench_mcap(Path(tmp), files)
    if not args.no_aravis:
        bench_aravis(args.frames, args.fps)
        bench_aravis(args.frames * 2, 100.0)


if __name__ == "__main__":
    tune_allocator()  # as every edgecal command does (importing edgecal does not)
    main()
