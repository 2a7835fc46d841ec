"""The live loop's supervision: open the camera (with back-off), read frames, hand each to the frame pipeline,
publish, report status, reload the config, stop.

State lives here (the camera, the sockets, the counters, the state for the status message); the work per
frame is edgecal.stream.frame_pipeline (check the images, track or search the boards, pose), and the
message is built whole by edgecal.publish.messages.pose_message. The loop is steered from outside only
through :meth:`LiveLoop.request_stop` and :meth:`LiveLoop.request_reload` (signal handlers call them), so a
signal never interrupts a frame half-way; :meth:`LiveLoop.abort` is the deadline behind a stop request.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections.abc import Callable

from edgecal.drivers.base import Source, StereoFrame
from edgecal.drivers.spec import SourceSpec
from edgecal.errors import DeviceError, DeviceLost, EdgecalError, InputError, clip, exception_summary
from edgecal.publish import pose_message, status_message
from edgecal.publish.outputs import LoopOutputs
from edgecal.publish.sinks import FrameOutput, build_sinks, close_all
from edgecal.stream.config import LiveConfig, load_live_config
from edgecal.stream.frame_pipeline import FramePipeline, capture_time_ns
from edgecal.stream.notify import SystemdNotifier
from edgecal.stream.opener import SourceOpener
from edgecal.stream.stats import LoopStats

log = logging.getLogger("edgecal.stream")

READ_SLICE_S = 0.2          # longest blocking read: a stop request is served within about this
# On a clean stop, the last poses and the "stopping" status may take this long to leave the socket (an abort
# after SIGTERM's grace period drops them): a subscriber learns the stream ended. Well inside TimeoutStopSec.
CLOSE_LINGER_S = 0.25
UNREADABLE_PAUSE_S = 0.05   # between reads while a source gives nothing but unreadable frames


def default_source_factory(spec: SourceSpec) -> Source:
    """The drivers' ``open_source`` (imported late so a robot without a camera library still replays)."""
    from edgecal.drivers.factory import open_source
    return open_source(spec)


class LiveLoop:
    """One live pose stream. ``run()`` blocks until a stop request (or the end of a finite source)."""

    def __init__(self, config: LiveConfig,
                 source_factory: Callable[[SourceSpec], Source] = default_source_factory,
                 notifier: SystemdNotifier | None = None) -> None:
        self.config = config
        self.source_factory = source_factory
        self.notifier = notifier or SystemdNotifier()
        self.stats = LoopStats(time.monotonic_ns())
        self.pipeline = pipeline_for(config)
        self.state = "starting"
        # Plain flags, not threading.Event: a signal handler that takes a lock the interrupted loop
        # already holds would deadlock.
        self._stop_requested = False
        self._stop_requested_ns = 0
        self._reload_requested = False
        self._source: Source | None = None
        self._outputs = LoopOutputs()                # the ZeroMQ stream and the sinks beside it (MCAP, Foxglove)
        # The camera and the socket are used under this lock, so that abort() (another thread, when a
        # frame takes too long after SIGTERM) can release them while the loop is busy detecting.
        self._io = threading.RLock()
        self._aborted = False
        self._ready_sent = False
        self._last_frame_ns = 0
        self._backoff_s = config.loop.reconnect_min_s
        self._next_open_ns = 0
        # Opening a camera can block for seconds (a GigE camera that does not answer); it runs in its own
        # thread so that status and the watchdog keep flowing meanwhile.
        self._opener: SourceOpener | None = None
        # After a reload that changed the source: the config to go back to if the new source does not open.
        self._revert_to: LiveConfig | None = None
        self._next_status_ns = 0
        # Why the state is what it is, for the status message: the camera's last problem and the last failed
        # reload's, kept apart so that a camera coming back does not hide that the new config was refused.
        self._camera_message = ""
        self._reload_message = ""
        self._last_error_log_ns = 0

    # -- requests from outside (signal handlers, other threads) -------------------------------------

    def request_stop(self) -> None:
        """Ask the loop to stop after the current frame (safe from a signal handler)."""
        self._stop_requested = True
        self._stop_requested_ns = time.monotonic_ns()

    def request_reload(self) -> None:
        """Ask the loop to reload its config file before the next frame (safe from a signal handler)."""
        self._reload_requested = True

    @property
    def stop_requested_ns(self) -> int:
        """CLOCK_MONOTONIC of the stop request (0: none yet)."""
        return self._stop_requested_ns

    def abort(self) -> None:
        """Release the camera and the socket now, from another thread, while the loop may still be inside a
        frame; the loop publishes nothing more and ends at its next check. For a stop deadline."""
        with self._io:
            if self._aborted:
                return
            self._aborted = True
            self._stop_requested = True
            self._release_io()
        log.info("stopped (aborted in frame) after %d frames, %.0f ms after the stop request", self.stats.frames,
                 (time.monotonic_ns() - self._stop_requested_ns) / 1e6 if self._stop_requested_ns else 0.0)

    # -- the loop ----------------------------------------------------------------------------------------

    def run(self) -> int:
        """Run until stopped; returns the exit code (0 after a stop request or the end of a replay)."""
        self._outputs.bind(self.config.publish)
        curve = self.config.publish.curve
        log.info("publishing on %s%s; source %s", self.config.publish.endpoint,
                 f" (CURVE, {len(curve.clients)} subscriber keys)" if curve else "", self.config.source.uri)
        try:
            self._outputs.sinks = build_sinks(self.config.outputs)
            self.warm_up()
            while not self._stop_requested:
                if self._reload_requested:
                    self._reload_requested = False
                    self._do_reload()
                now = time.monotonic_ns()
                if now >= self._next_status_ns:
                    self._report(now)
                if self._source is None:
                    self._try_open(now)
                    continue
                if not self._step():
                    break
            return 0
        finally:
            with self._io:
                aborted = self._aborted
                if not aborted:
                    self._release_io(CLOSE_LINGER_S)
            self.pipeline.close()
            if self._opener is not None:
                self._opener.cancel()
                self._opener = None
            if aborted:
                # abort() closed the camera and socket under the running frame: whatever that frame raised
                # is the abort's doing, not a failure, so the aborted loop ends cleanly
                return 0  # noqa: B012
            took = f" ({(time.monotonic_ns() - self._stop_requested_ns) / 1e6:.0f} ms after the stop request)" \
                if self._stop_requested_ns else ""
            log.info("stopped after %d frames%s", self.stats.frames, took)

    def warm_up(self) -> None:
        """Run the per-frame path once on a drawn chessboard (FramePipeline.warm_up: numba's cache, OpenCV's
        first calls and the first large buffers are not paid by the first camera frame); then freeze what is
        loaded out of the garbage collector's full collections."""
        t0 = time.monotonic()
        self.pipeline.warm_up()
        # Everything loaded so far (numba, scipy, OpenCV bindings: hundreds of thousands of objects) lives as
        # long as the process: frozen out of the collector's view, a full collection no longer walks them all,
        # which otherwise stalls one frame in a few hundred by ~60 ms.
        gc.collect()
        gc.freeze()
        log.info("detector ready (%.1f s)", time.monotonic() - t0)

    def _try_open(self, now: int) -> None:
        """Open the source when its back-off has passed, in a background thread; take its result when done."""
        if self._opener is None:
            if now < self._next_open_ns:
                time.sleep(min(READ_SLICE_S, (self._next_open_ns - now) / 1e9))
                return
            self._opener = SourceOpener(self.config.source, self.source_factory)
            return
        if not self._opener.wait(READ_SLICE_S):
            if not self._ready_sent and self._opener.elapsed_s > self.config.loop.camera_lost_after_s:
                # A camera that does not answer: the service is up and says so, waiting for it.
                self.state = "camera-lost"
                self._camera_message = f"opening {self.config.source.uri} takes long"
                self._send_ready(f"waiting for the camera {self.config.source.uri}")
            return
        source, error = self._opener.result()
        self._opener = None
        if source is None:
            if self._revert_to is not None:
                self._revert_source(error)
                return
            self._camera_lost(error)
            return
        self._revert_to = None
        with self._io:
            if self._aborted or self._stop_requested:
                source.close()
                return
            self._source = source
        self._last_frame_ns = time.monotonic_ns()
        self.pipeline.reset()
        if self.state == "camera-lost":
            log.info("camera %s reopened", self.config.source.uri)
            self.stats.reconnects += 1
        self.state = "running" if self._ready_sent else "starting"
        self._camera_message = ""

    def _camera_lost(self, why: str) -> None:
        self._close_source()
        if self.state != "camera-lost":
            log.warning("camera lost: %s; reopening with back-off", why)
        self.state = "camera-lost"
        self._camera_message = clip(why)
        self._next_open_ns = time.monotonic_ns() + int(self._backoff_s * 1e9)
        self._backoff_s = min(self._backoff_s * 2, self.config.loop.reconnect_max_s)
        # The loop runs and reports; a camera absent at boot must not keep the service "starting" until
        # systemd's start timeout kills it.
        self._send_ready(f"camera-lost: waiting for {self.config.source.uri}")

    def _revert_source(self, why: str) -> None:
        """The source of a reloaded config does not open: go back to the config whose source was running."""
        old, self._revert_to = self._revert_to, None
        assert old is not None
        try:
            self._apply(old, revert_to=None)
        except Exception as exc:  # noqa: BLE001 - the old socket cannot be bound again: keep the new one
            log.error("cannot go back to the previous config: %s", exc)
        self._reload_failed(f"{why}; back to the previous source")

    def _send_ready(self, status: str) -> None:
        """READY=1, once."""
        if not self._ready_sent:
            self._ready_sent = True
            self.notifier.ready(status)
            log.info("ready: %s", status)

    def _release_io(self, linger_s: float = 0.0) -> None:
        """Say "stopping", release the camera, publish a last status and close the socket (under _io);
        ``linger_s``: how long the last messages may take to leave."""
        self.state = "stopping"
        self.notifier.stopping()
        self._close_source()
        if self._outputs.publisher is not None:
            self._report(time.monotonic_ns())
        self._outputs.close(linger_s)

    def _close_source(self) -> None:
        with self._io:
            if self._source is not None:
                src, self._source = self._source, None
                try:
                    self.stats.source_dropped(src.dropped)
                finally:
                    self.stats.source_closed()
                    src.close()

    def _step(self) -> bool:
        """Read and process one frame; False when a finite source has ended and the loop should stop."""
        t_read = time.monotonic_ns()
        try:
            with self._io:
                if self._source is None:         # released by abort()
                    return True
                frame = self._source.read(READ_SLICE_S)
                self.stats.source_dropped(self._source.dropped)
        except InputError as exc:                # an unreadable frame of a replay: skip it
            self.stats.corrupt_frames += 1
            self._rate_limited_error(f"unreadable frame skipped: {exc}")
            if time.monotonic_ns() - t_read < 10**6 and time.monotonic_ns() - self._last_frame_ns > 10**9:
                # Nothing but unreadable frames for a second (a folder of broken files, no descriptors
                # left): do not spin through them at full speed.
                time.sleep(UNREADABLE_PAUSE_S)
            return True
        except Exception as exc:  # noqa: BLE001 - DeviceError, or a driver's own bug: the camera may come back
            if not isinstance(exc, DeviceError):
                self.stats.errors += 1
                self._rate_limited_error(f"error while reading {self.config.source.uri}: {exception_summary(exc)}",
                                         exc_info=True)
            silent_s = (time.monotonic_ns() - self._last_frame_ns) / 1e9
            # A camera that is gone (unplugged, its capture thread dead) is reopened at once; one that is
            # only silent (a timeout: slow, or waiting for a trigger) gets camera_lost_after_s first.
            if isinstance(exc, DeviceLost) or silent_s > self.config.loop.camera_lost_after_s:
                self._camera_lost(str(exc) if isinstance(exc, DeviceError) else exception_summary(exc))
            elif time.monotonic_ns() - t_read < 10**6:
                time.sleep(0.02)                 # the error came at once (a dead capture thread): don't spin
            return True
        if frame is None:
            if self.config.loop.stop_at_end:
                log.info("source %s ended", self.config.source.uri)
                return False
            self._camera_lost("the source ended")
            return True
        if not isinstance(frame, StereoFrame):
            raise DeviceError(f"{self.config.source.uri} delivers single images; the live loop needs a stereo "
                              "source (stereo:LEFT,RIGHT, depthai:, or a replay of left/ and right/)")
        self._last_frame_ns = time.monotonic_ns()
        self._backoff_s = self.config.loop.reconnect_min_s
        self._process(frame)
        if self.state != "running":
            self.state = "running"
            self._send_ready(f"first frame processed; publishing on {self.config.publish.endpoint}")
        return True

    def _process(self, frame: StereoFrame) -> None:
        """Pose one stereo frame (edgecal.stream.frame_pipeline), count what happened, publish the message."""
        cfg = self.config
        result = self.pipeline.process(frame)
        if result.tracked:
            self.stats.tracked_frames += 1
        if result.problems:
            self.stats.corrupt_frames += 1
            self._rate_limited_error(f"corrupt frame {frame.left.seq}: {'; '.join(result.problems)}")
        if result.error is not None:     # a bug: logged and counted, the daemon goes on
            self.stats.errors += 1
            self._rate_limited_error(f"error while processing frame {frame.left.seq}: "
                                     f"{exception_summary(result.error)}", exc_info=result.error)
        now = time.monotonic_ns()
        capture_ns, basis = capture_time_ns(frame, now, cfg.source.driver in ("replay", "mcap", "rosbag"))
        msg = pose_message(result.pose, frame.left.seq, frame.stamp_ns, now, cfg.outputs.frame_id,
                           cfg.outputs.child_frame_id, capture_ns=capture_ns, latency_from=basis,
                           detection=result.detection)
        out = FrameOutput(frame, result.pose, msg, result.detections, capture_ns)
        with self._io:
            self._outputs.send("frame", out)
        self.stats.frame_done(now - capture_ns, result.pose.valid, result.failed_images)

    @property
    def _last_message(self) -> str:
        """The status message: the failed reload's reason and the camera's problem, whichever there are."""
        return clip("; ".join(m for m in (self._reload_message, self._camera_message) if m))

    def _report(self, now: int) -> None:
        """Once a period: log the figures at INFO, publish them as status, pet the watchdog."""
        figures = self.stats.period(now)
        lat = figures["latency_ms"]
        log.info("%s: %.1f fps, latency median %s ms p99 %s ms, %d dropped, %d detection failures, "
                 "%d corrupt, %d invalid poses%s", self.state, figures["fps"], lat["median"], lat["p99"],
                 figures["dropped_frames"], figures["detection_failures"], figures["corrupt_frames"],
                 figures["poses_invalid"], f" ({self._last_message})" if self._last_message else "")
        figures["source"] = self.config.source.uri
        with self._io:
            if self._outputs.publisher is None and not self._aborted and self.state != "stopping":
                try:                             # lost in a failed reload: tried once per status period
                    self._outputs.rebind(self.config.publish)
                except EdgecalError as exc:
                    self._rate_limited_error(f"pose stream not bound: {exc}")
            figures.update(self._outputs.counters())
            self._outputs.send("status", status_message(self.state, figures, now, self._last_message))
        self.notifier.watchdog()
        self.notifier.status(f"{self.state}: {figures['fps']} fps, p99 {lat['p99']} ms")
        self._next_status_ns = now + int(self.config.loop.status_period_s * 1e9)

    def _reload_failed(self, why: str) -> None:
        self.stats.reload_failures += 1
        # Kept short: it is repeated in every status message until the next good reload.
        self._reload_message = clip(f"reload failed, keeping the running config: {why}")
        log.error("%s", self._reload_message)
        self.notifier.ready()

    def _do_reload(self) -> None:
        """Reload the config file. A reload never ends the process: a file that does not load or validate,
        an endpoint that cannot be bound or any other failure is logged, and the running config kept (with
        its socket restored if the new one was half set up). The camera is reopened only when the source
        settings changed; if the new source then cannot be opened, the old config comes back."""
        self.notifier.reloading()
        try:
            new = load_live_config(self.config.path)
        except EdgecalError as exc:
            self._reload_failed(str(exc))
            return
        except Exception as exc:  # a bug in validation must not end a daemon: log it, keep running
            log.exception("unexpected error while reloading %s", self.config.path)
            self._reload_failed(f"{self.config.path}: {exception_summary(exc)}")
            return
        try:
            self._apply(new, revert_to=self.config if self._source is not None else None)
        except Exception as exc:  # noqa: BLE001 - a socket that cannot be bound, or a bug: keep the running config
            self._reload_failed(str(exc) if isinstance(exc, EdgecalError) else exception_summary(exc))
            return
        self._reload_message = ""
        log.info("config %s reloaded", new.path)
        self.notifier.ready()

    def _apply(self, new: LiveConfig, revert_to: LiveConfig | None) -> None:
        """Make ``new`` the running config. What can fail is built first; on a failure the running config is
        left as it was (socket included) and the error raised. ``revert_to``: the config to come back to if
        the new source cannot be opened (the old source was running)."""
        old = self.config
        if self._aborted:
            return
        pipeline = pipeline_for(new, self.pipeline)
        # Opened before the running ones are let go: if one fails, they all stay.
        sinks = build_sinks(new.outputs) if new.outputs != old.outputs else None
        with self._io:
            old_sinks = self._outputs.reconfigure(new.publish, old.publish, sinks)
        close_all(old_sinks)
        if new.source != old.source:
            self._close_source()            # reopened with the new settings on the next pass
            self._next_open_ns = 0
            self._revert_to = revert_to
        self.config = new
        self.pipeline = pipeline
        self._backoff_s = new.loop.reconnect_min_s

    def _rate_limited_error(self, text: str, exc_info: bool | BaseException = False) -> None:
        """Log at most one such error per status period (a broken camera must not flood the journal)."""
        now = time.monotonic_ns()
        if now - self._last_error_log_ns >= int(self.config.loop.status_period_s * 1e9):
            self._last_error_log_ns = now
            log.error("%s", text, exc_info=exc_info)


def pipeline_for(config: LiveConfig, running: FramePipeline | None = None) -> FramePipeline:
    """The frame pipeline of ``config`` (sharing the ``running`` one's worker thread, after a reload)."""
    parts = (config.target, config.cameras, config.detector, config.pose, config.tracking)
    return running.reconfigured(*parts) if running is not None else FramePipeline(*parts)


def run_live(config_path: str, notifier: SystemdNotifier | None = None) -> int:
    """Load ``config_path`` (exiting on a bad field before any device opens) and run the loop."""
    return LiveLoop(load_live_config(config_path), notifier=notifier).run()
