"""The SLAM estimator beside the frontend: in this process, or in a second one.

The stage's frontend (decoding, image preparation, KLT tracking) and its estimator
(keyframe rule, GTSAM smoother, loop closure) take turns for Python's GIL when they
share a process: GTSAM's pybind11 calls and the estimator's NumPy-heavy Python hold it
while they run, so on two cores the threads barely overlap. `EstimatorProcess` runs the
estimator in a process of its own (started with "spawn": never a fork of this threaded
process), fed through a pipe:

    parent -> worker   ("frame", sequence, tracks or None), ("finish",)
    worker -> parent   ("frame", sequence, gyro bias, is keyframe), ("log", record), then
                       ("result", SlamResult, CPU seconds) or ("error", exception, traceback)

The frontend images that keyframe descriptors are computed on (`describe`) go through a
shared-memory ring of `slots` images: the parent copies each estimated image into slot
`sequence % slots` before it sends the frame, and reuses a slot only once the worker has
answered for the frame that held it. A thread of the parent ("slam-estimator-feed")
writes the frames into the pipe: a pipe holds only 64 KiB (four images' tracks), so a
frontend writing them itself would stall whenever a keyframe keeps the worker busy
(50-220 ms, up to a second, against 9 ms an image for the frontend), and the two would
take turns instead of overlapping. The worker reads the slot only when the frame turns
out to be a keyframe. The estimator sees the same tracks, the same images and the same
order as in-process, and the frontend gets the same biases (`publish`, the stage's
`BiasBoard`), so the result is the same to the bit.

`InProcessEstimator` has the same interface and runs the estimator in the caller's
thread (tiny inputs, one core, tests that patch the estimator).

The worker's log records are logged by the parent (its handlers, its format), at the
level the parent's "postproc.slam" logger has when the worker starts. An error in the
worker is raised in the parent as itself (pickled: a StageError stays a
StageError), with the worker's traceback as a note. The worker ignores SIGINT (the
parent decides), and stops when the parent closes the pipe or dies (its next read finds
the pipe closed); `close` terminates it if it is still busy.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import logging
import multiprocessing
import os
import pickle
import queue
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from postproc.slam.estimator import SlamEstimator, SlamResult
from postproc.slam.frontend import Image
from postproc.slam.inputs import Frame
from postproc.slam.loop_closure import Descriptors, orb_descriptors
from postproc.slam.options import EstimatorOptions
from postproc.slam.types import FloatArray, FrameTracks, ImuSamples, IntArray
from postproc.slam.visual_only import VisualOnlyEstimator
from shared.calibration.kalibr import ImuNoise
from shared.errors import StageError

Estimator = SlamEstimator | VisualOnlyEstimator
Publish = Callable[[int, FloatArray | None], None]
"""Called with (sequence, gyro bias) once the estimator is done with an image."""
OnKeyframe = Callable[[Frame], None]
"""Called with the frame of each image the estimator made a keyframe, in order."""

MIN_FRAMES = 300
"""'auto' runs the estimator in a second process from this many images on (10 s at
30 fps): starting it costs about 0.6 CPU seconds (a fresh interpreter importing NumPy,
OpenCV and GTSAM)."""


@dataclass(frozen=True)
class EstimatorSetup:
    """What an estimator is built from.

    imu / imu_noise: the IMU samples and noise (both None: the visual-only baseline).
    image_shape: (rows, cols) of the frontend images (uint8) `describe` works on.
    """

    options: EstimatorOptions
    focal_px: float
    imu_from_cam: FloatArray
    imu: ImuSamples | None
    imu_noise: ImuNoise | None
    image_shape: tuple[int, int]

    def initial_gyro_bias(self) -> FloatArray | None:
        """The gyro bias the frontend seeds with before the estimator has one."""
        return np.zeros(3) if self.imu is not None and self.imu_noise is not None else None

    def build(self) -> Estimator:
        """The estimator (SlamEstimator with an IMU, VisualOnlyEstimator without)."""
        if self.imu is None or self.imu_noise is None:
            return VisualOnlyEstimator(
                self.options, focal_px=self.focal_px, imu_from_cam=self.imu_from_cam
            )
        return SlamEstimator(
            self.options,
            focal_px=self.focal_px,
            imu_from_cam=self.imu_from_cam,
            imu=self.imu,
            imu_noise=self.imu_noise,
        )


def gyro_bias(estimator: Estimator) -> FloatArray | None:
    """The gyro bias (rad/s) of the estimator's last keyframe (zero before the start; None
    without an IMU): what the frontend's rotation seeds use."""
    if not isinstance(estimator, SlamEstimator):
        return None
    backend = estimator.backend
    if not backend.num_keyframes:
        return np.zeros(3)
    return np.asarray(backend.bias_of(backend.num_keyframes - 1).gyroscope(), dtype=np.float64)


def describe(image: Image, tracks: FrameTracks) -> tuple[IntArray, Descriptors]:
    """ORB descriptors at the tracked features of the frontend image `image`."""
    return orb_descriptors(image, tracks.pixels)


def use_a_process(
    mode: str, frames: int, *, busy_cores: float | None = None, probe: BusyProbe | None = None
) -> bool:
    """Whether the stage runs its estimator in a second process: `mode` "on", "off", or
    "auto": at least `MIN_FRAMES` images, two cores this process may use, and one of them
    idle (`busy_cores`, else what `probe` measured, else the cores busy now by
    `busy_cores_now`, else the 1-minute load average, at most the cores less one). The
    choice changes only the speed, never the result."""
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"estimator_process {mode!r}: expected 'auto', 'on' or 'off'")
    if mode != "auto":
        return mode == "on"
    if multiprocessing.current_process().daemon:
        return False  # a daemonic process may not start one
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cores = cores or 1
    if frames < MIN_FRAMES or cores < 2:
        return False
    if busy_cores is None:
        busy_cores = probe.result() if probe is not None else busy_cores_now()
    if busy_cores is None:
        busy_cores = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    # On busy cores the worker only adds its cost (about 3 CPU s per 40 s of video).
    return busy_cores <= cores - 1


#: How long `busy_cores_now` watches the CPUs.
BUSY_WINDOW_S = 0.5


def busy_cores_now(window_s: float = BUSY_WINDOW_S) -> float | None:
    """Cores busy with other work over the next `window_s` seconds (`BusyProbe`, waited
    for); None where there are no CPU counters to read.

    The 1-minute load average lags: just after another job it still counts that job's
    cores for a minute or more, while a SLAM run lasts minutes to hours.
    """
    return BusyProbe(window_s).result()


class BusyProbe:
    """The cores busy over a window of `window_s` seconds from now, from the kernel's CPU
    counters (/proc/stat), measured in a thread of its own: the stage starts it before its
    setup work, so that the window overlaps that work instead of adding to the wall time
    (stop 52: the window was 0.5 of a 60 s run's 21-24 s). The CPU time this process
    spent in the window is left out: it is the stage's own work, not another program's
    load. `result` waits for the window to end; `cancel` ends it at once (a run that needs
    no answer, or fails first, leaves no thread behind)."""

    def __init__(self, window_s: float = BUSY_WINDOW_S) -> None:
        self._busy: float | None = None
        self._cancelled = threading.Event()
        self._thread = threading.Thread(
            target=self._measure, args=(window_s,), name="slam-busy-probe", daemon=True
        )
        self._thread.start()

    def _measure(self, window_s: float) -> None:
        try:
            before, own_before, start = _read_proc_stat(), time.process_time(), time.monotonic()
            if self._cancelled.wait(window_s):
                return
            after, own, elapsed = (
                _read_proc_stat(),
                time.process_time() - own_before,
                time.monotonic() - start,
            )
        except OSError:
            return
        busy = busy_cores_between(before, after)
        if busy is not None and elapsed > 0:
            self._busy = max(busy - own / elapsed, 0.0)

    def result(self) -> float | None:
        """Cores busy with other work over the window (None where /proc/stat is missing,
        or after `cancel`)."""
        self._thread.join()
        return self._busy

    def cancel(self) -> None:
        """End the window now (no answer) and wait for the thread."""
        self._cancelled.set()
        self._thread.join()


def _read_proc_stat() -> str:
    return Path("/proc/stat").read_text(encoding="ascii")


def busy_cores_between(before: str, after: str) -> float | None:
    """Cores busy between two readings of /proc/stat (its "cpu" line: user, nice, system,
    idle, iowait, irq, softirq, steal, ... in clock ticks; idle and iowait are idle), as
    busy ticks over all ticks times the CPUs its "cpuN" lines count. None when a reading
    has no "cpu" line or no tick went by."""

    def totals(text: str) -> tuple[int, int, int] | None:
        cpus = 0
        line = None
        for row in text.splitlines():
            if row.startswith("cpu "):
                line = row
            elif row.startswith("cpu") and row[3:4].isdigit():
                cpus += 1
        if line is None:
            return None
        ticks = [int(v) for v in line.split()[1:9]]
        idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)
        return sum(ticks), idle, cpus

    first, second = totals(before), totals(after)
    if first is None or second is None:
        return None
    elapsed = second[0] - first[0]
    if elapsed <= 0:
        return None
    busy = elapsed - (second[1] - first[1])
    return max(second[2], 1) * busy / elapsed


class EstimatorRunner(Protocol):
    """Where the stage sends its tracked images (`InProcessEstimator`, `EstimatorProcess`)."""

    worker_cpu_s: float
    """CPU seconds of a second process (0 without one), after `finish`."""

    def submit(self, sequence: int, frame: Frame, tracks: FrameTracks | None, image: Image) -> None:
        """Image `sequence` (0, 1, ...): estimate `tracks` (None: only pass it on)."""

    def finish(self) -> SlamResult:
        """The estimator's result once every submitted image is done."""

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds of the estimator's threads (after `finish`)."""

    def close(self) -> None:
        """Stop (idempotent; a worker still running is ended)."""


class InProcessEstimator:
    """The estimator in the calling thread: `submit` estimates before it returns."""

    def __init__(self, setup: EstimatorSetup, *, publish: Publish, on_keyframe: OnKeyframe):
        self.estimator = setup.build()
        self._publish = publish
        self._on_keyframe = on_keyframe
        self.worker_cpu_s = 0.0

    def submit(self, sequence: int, frame: Frame, tracks: FrameTracks | None, image: Image) -> None:
        if tracks is not None:
            decision = self.estimator.process(tracks, functools.partial(describe, image, tracks))
            if decision.is_keyframe:
                self._on_keyframe(frame)
        self._publish(sequence, gyro_bias(self.estimator))

    def finish(self) -> SlamResult:
        return self.estimator.finish()

    def cpu_seconds(self) -> dict[str, float]:
        return {}  # the caller's thread: the caller counts it

    def close(self) -> None:
        pass


class ImageRing:
    """`slots` frontend images (uint8, `shape`) in shared memory, by sequence number."""

    def __init__(self, shape: tuple[int, int], slots: int, *, name: str | None = None) -> None:
        self.shape = shape
        self.slots = slots
        size = max(slots * shape[0] * shape[1], 1)
        self._memory = SharedMemory(name=name, create=name is None, size=size)
        self._images: np.ndarray[Any, np.dtype[np.uint8]] = np.ndarray(
            (slots, *shape), dtype=np.uint8, buffer=self._memory.buf
        )

    @property
    def name(self) -> str:
        """The shared-memory block's name (to attach to it from another process)."""
        return self._memory.name

    def put(self, sequence: int, image: Image) -> None:
        """Store image `sequence` (its slot must be free: see EstimatorProcess)."""
        if image.shape != self.shape:
            raise StageError(
                f"frontend image {sequence}: {image.shape[1]}x{image.shape[0]} px, expected "
                f"{self.shape[1]}x{self.shape[0]} (the images changed size mid-recording?)"
            )
        self._images[sequence % self.slots] = image

    def get(self, sequence: int) -> Image:
        """A copy of image `sequence`."""
        image: Image = self._images[sequence % self.slots].copy()
        return image

    def close(self, *, unlink: bool = False) -> None:
        """Detach (and, by the process that made it, free) the block."""
        del self._images
        self._memory.close()
        if unlink:
            self._memory.unlink()


class EstimatorProcess:
    """The estimator in a second process, fed image by image (module docstring).

    `submit` copies the image into the ring and sends the tracks; it waits only when the
    worker still holds the ring slot it needs (`slots` images behind). A thread of this
    process ("slam-estimator-link") reads the worker's answers: it calls `publish` with
    each image's gyro bias and `on_keyframe` with each keyframe's frame, in order.
    Use it as a context manager (or call `close`): the worker never outlives it.
    """

    def __init__(
        self,
        setup: EstimatorSetup,
        *,
        publish: Publish,
        on_keyframe: OnKeyframe,
        slots: int,
    ) -> None:
        self._publish = publish
        self._on_keyframe = on_keyframe
        self._ring = ImageRing(setup.image_shape, slots)
        self._slots = slots
        context = multiprocessing.get_context("spawn")
        worker_inbox, self._inbox = context.Pipe(duplex=False)
        self._outbox, worker_outbox = context.Pipe(duplex=False)
        self._process = context.Process(
            target=_serve,
            args=(
                worker_inbox,
                worker_outbox,
                setup,
                self._ring.name,
                slots,
                logging.getLogger("postproc.slam").getEffectiveLevel(),
            ),
            name="slam-estimator",
            daemon=True,
        )
        self._changed = threading.Condition()
        self._answered = -1  # the last image the worker is done with
        self._frames: dict[int, Frame] = {}  # submitted, not yet answered
        self._ended = False  # the link thread is done (result, error or a dead worker)
        self._failure: BaseException | None = None
        self._result: SlamResult | None = None
        self._cpu: dict[str, float] = {}
        self.worker_cpu_s = 0.0
        """The worker process's CPU seconds, all of them (after `finish`)."""
        self._closed = False
        try:
            with _sigint_ignored():
                self._process.start()
        except BaseException:
            self._ring.close(unlink=True)
            raise
        finally:
            # The worker's ends belong to it now: closing ours lets each side see the
            # other's end (EOF) when it goes.
            worker_inbox.close()
            worker_outbox.close()
        self._link = threading.Thread(target=self._receive, name="slam-estimator-link")
        self._link.start()
        # What the feed thread writes into the pipe, in order; None ends it.
        self._outgoing: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._feed = threading.Thread(target=self._send, name="slam-estimator-feed")
        self._feed.start()

    def __enter__(self) -> EstimatorProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def submit(self, sequence: int, frame: Frame, tracks: FrameTracks | None, image: Image) -> None:
        with self._changed:
            self._changed.wait_for(lambda: self._answered >= sequence - self._slots or self._ended)
            if self._ended:
                self._raise_failure()
            self._frames[sequence] = frame
        if tracks is not None:
            self._ring.put(sequence, image)
        self._outgoing.put(("frame", sequence, tracks))

    def finish(self) -> SlamResult:
        self._outgoing.put(("finish",))
        self._outgoing.put(None)
        self._feed.join()
        self._link.join()
        if self._result is None:
            self._raise_failure()
        assert self._result is not None
        return self._result

    def cpu_seconds(self) -> dict[str, float]:
        return dict(self._cpu)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._outgoing.put(None)
        if self._result is None:  # still busy (an error here, Ctrl-C): no need to wait
            self._process.terminate()
        self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()
        self._feed.join()  # (a write into the dead worker's pipe fails at once)
        self._inbox.close()
        self._link.join()
        self._outbox.close()
        self._ring.close(unlink=True)

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise self._failure
        self._process.join(timeout=10)
        raise StageError(
            f"the SLAM estimator process ended unexpectedly (exit code {self._process.exitcode})"
        )

    def _send(self) -> None:
        """The feed thread: the queued messages into the pipe, until None or a dead worker
        (the link thread then sees it end, and `submit` or `finish` says why)."""
        try:
            while (message := self._outgoing.get()) is not None:
                try:
                    self._inbox.send(message)
                except OSError:  # BrokenPipeError: the worker is gone
                    return
        finally:
            self._cpu["estimator-feed"] = time.thread_time()

    def _receive(self) -> None:
        """The link thread: the worker's answers, until its result, error or end."""
        try:
            while True:
                try:
                    message = self._outbox.recv()
                except (EOFError, OSError):
                    return  # the worker is gone (`_raise_failure` says how)
                if message[0] == "frame":
                    _, sequence, bias, is_keyframe = message
                    self._publish(sequence, bias)
                    with self._changed:
                        frame = self._frames.pop(sequence)
                        self._answered = sequence
                        self._changed.notify_all()
                    if is_keyframe:
                        self._on_keyframe(frame)
                elif message[0] == "log":  # the worker's, through this process's handlers
                    record = message[1]
                    logging.getLogger(record.name).handle(record)
                elif message[0] == "result":
                    _, self._result, threads_s, self.worker_cpu_s = message
                    self._cpu.update(threads_s)
                    return
                else:
                    _, error, trace = message
                    error.add_note(f"in the SLAM estimator process:\n{trace}")
                    self._failure = error
                    return
        except BaseException as error:  # (a keyframe not written, say): raised by submit or finish
            self._failure = error
        finally:
            self._cpu["estimator-link"] = time.thread_time()
            with self._changed:
                self._ended = True
                self._changed.notify_all()


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored (main thread only): a process started meanwhile inherits that, so
    a Ctrl-C during its start (imports) does not print a second traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _describe_slot(
    ring: ImageRing, sequence: int, tracks: FrameTracks
) -> tuple[IntArray, Descriptors]:
    return describe(ring.get(sequence), tracks)


class _LogToParent(logging.Handler):
    """The worker's log records, sent to the parent (which logs them as its own)."""

    def __init__(self, outbox: Connection) -> None:
        super().__init__()
        self._outbox = outbox

    def emit(self, record: logging.LogRecord) -> None:
        try:
            # Made picklable as logging.handlers.QueueHandler does: the message formatted,
            # the traceback as text.
            record = copy.copy(record)
            record.msg = record.getMessage()
            record.args = None
            if record.exc_info:
                record.exc_text = logging.Formatter().formatException(record.exc_info)
                record.exc_info = None
            self._outbox.send(("log", record))
        except Exception:
            self.handleError(record)


def _serve(
    inbox: Connection,
    outbox: Connection,
    setup: EstimatorSetup,
    ring_name: str,
    slots: int,
    log_level: int,
) -> None:
    """The worker: estimate each image the parent sends, answer with its gyro bias."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    root = logging.getLogger()
    root.handlers[:] = [_LogToParent(outbox)]
    root.setLevel(log_level)
    ring: ImageRing | None = None
    try:
        ring = ImageRing(setup.image_shape, slots, name=ring_name)
        estimator = setup.build()
        start_s = time.thread_time()
        opencv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)  # as the stage sets it around its image loop
        while True:
            try:
                message = inbox.recv()
            except EOFError:
                return  # the parent is gone
            if message[0] == "finish":
                break
            _, sequence, tracks = message
            is_keyframe = False
            if tracks is not None:
                decision = estimator.process(
                    tracks, functools.partial(_describe_slot, ring, sequence, tracks)
                )
                is_keyframe = decision.is_keyframe
            outbox.send(("frame", sequence, gyro_bias(estimator), is_keyframe))
        cv2.setNumThreads(opencv_threads)
        result = estimator.finish()
        cpu = {"estimator-start": start_s, "estimator": time.thread_time() - start_s}
        outbox.send(("result", result, cpu, time.process_time()))
    except BaseException as error:  # handed to the parent, raised there
        trace = traceback.format_exc()
        try:
            pickle.dumps(error)
        except Exception:  # an error that does not pickle: its words
            error = StageError(f"{type(error).__name__}: {error}")
        with contextlib.suppress(OSError):  # the parent is gone
            outbox.send(("error", error, trace))
    finally:
        if ring is not None:
            ring.close()
        outbox.close()
