"""Dive computers: Shearwater serial download, a simulated Shearwater, logbook importers.

protocol.py (framing, services, compression; pure), logformat.py (Petrel Native Format
logs; pure), download.py (the serial client), simulator.py (the simulated unit on a pty),
importers/ (Subsurface XML, UDDF, Shearwater Cloud CSV). Output: a dive folder
(shared/formats/diveprofile.py).
"""
