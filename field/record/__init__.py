"""The field logger: live camera/IMU recording to MCAP, live preview, inspect and recover.

Layers: `timing` (pure clock math), `sources/` (devices behind one `CameraSource`
protocol: DepthAI OAK, simulated OAK-like rig), `recorder` (bounded queues, rotation,
crash-safe flushing), `preview_bus` (zenoh publisher, read-only) and `preview_web`
(the boat's local web page), `recover` and `inspect` (archive tools). The CLI lives in
`field/commands/record.py`.
"""
