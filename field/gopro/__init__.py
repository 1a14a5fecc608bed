"""GoPro MP4 files: our own GPMF and MP4 readers and writers.

- `gpmf`: KLV parsing, streams with their SCAL/units/TSMP/STMP/ORIN, GPMF encoding.
- `mp4`: box walker and per-track sample tables (offsets, sizes, times, keyframes).
- `timing`: per-sample times on the video's clock (pure math).
- `telemetry`: whole-file streams with times, CSV export, summaries.
- `writer`: GoPro-like MP4 files (H.264 + 'gpmd'), IMU payloads, chapter naming.
- `cameras`: the camera database: intrinsics guess, IMU axes (ORIN) to the body frame.
- `annexb`: MP4 (length-prefixed) video packets to Annex B with in-band parameter sets.
- `salvage`: packets and telemetry of unfinalised files (no moov box).
- `importer`: chapters of a recording (or a whole DCIM/ folder) into session folders.
- `frames`: decoding frames straight from an MP4, to check an import.
"""
