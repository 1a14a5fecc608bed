"""How fast the simulator renders: ms per frame and the projected time of a survey.

    .venv/bin/python bench/bench_render.py [--frames 60] [--width 640 --height 360]
        [--survey-seconds 10]

Prints the scene build time, the per-frame render time (one process), the PNG encoding
time, and the projected wall time of the default survey (2 sessions x 60 s x 15 fps =
1800 frames) on 2 worker processes. With --survey-seconds it also times a real
`sim.survey.run` of that length (1 session, 2 workers, video included).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from sim.survey import SurveyOptions, SurveySimulator, run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--survey-seconds", type=float, default=0.0)
    args = parser.parse_args()
    cv2.setNumThreads(1)

    options = SurveyOptions(width=args.width, height=args.height, duration_s=60.0)
    sim = SurveySimulator(options)
    start = time.perf_counter()
    _ = sim.scene
    scene_s = time.perf_counter() - start
    start = time.perf_counter()
    _ = sim.renderer
    renderer_s = time.perf_counter() - start
    stamps = sim.sessions[0].frame_stamps_cam_ns
    pick = np.linspace(0, len(stamps) - 1, args.frames).astype(int)
    sim.renderer.prepare()
    render_ms, encode_ms, cpu_ms = [], [], []
    for i in pick:
        t0 = time.perf_counter()
        c0 = time.process_time()
        frame = sim.render_frame(0, int(stamps[i]), frame_index=int(i))
        cpu_ms.append((time.process_time() - c0) * 1e3)
        t1 = time.perf_counter()
        gray = cv2.cvtColor(frame.image_rgb, cv2.COLOR_RGB2GRAY)
        cv2.imencode(".png", gray)
        t2 = time.perf_counter()
        render_ms.append((t1 - t0) * 1e3)
        encode_ms.append((t2 - t1) * 1e3)
    render = np.array(render_ms)
    cpu = np.array(cpu_ms)
    encode = np.array(encode_ms)
    total_frames = 2 * 60 * 15
    # Workers render in parallel; the parent encodes PNGs (and H.264) while they render.
    projected_s = total_frames * max(render.mean() / 2.0, encode.mean()) / 1e3 + scene_s
    idle_s = total_frames * max(cpu.mean() / 2.0, encode.mean()) / 1e3
    print(f"cpu cores: {os.cpu_count()}  image: {args.width}x{args.height}")
    print(f"scene build (textures): {scene_s:.1f} s   renderer set-up: {renderer_s:.2f} s")
    print(
        f"render: {render.mean():.1f} ms/frame mean, {np.median(render):.1f} median, "
        f"{render.max():.1f} max over {len(render)} frames (1 process)"
    )
    print(f"render CPU time: {cpu.mean():.1f} ms/frame (what an idle core would take)")
    print(f"png encode (gray): {encode.mean():.1f} ms/frame")
    print(
        f"projected default survey ({total_frames} frames, 2 workers): "
        f"{projected_s:.0f} s = {projected_s / 60:.1f} min at this load (without H.264); "
        f"rendering alone on 2 idle cores: {idle_s:.0f} s"
    )
    print(f"load average now: {os.getloadavg()[0]:.1f}")
    if args.survey_seconds > 0:
        with tempfile.TemporaryDirectory() as tmp:
            opts = SurveyOptions(
                sessions=1, duration_s=args.survey_seconds, width=args.width, height=args.height
            )
            start = time.perf_counter()
            run(opts, Path(tmp) / "survey")
            elapsed = time.perf_counter() - start
            frames = int(args.survey_seconds * opts.fps)
            print(
                f"real survey of {args.survey_seconds:.0f} s ({frames} frames, video on): "
                f"{elapsed:.1f} s, {elapsed / frames * 1e3:.0f} ms/frame end to end"
            )


if __name__ == "__main__":
    main()
