"""Make a session folder a valid rosbag2 bag: a `metadata.yaml` describing its MCAP files.

`ros2 bag` and `rosbags` open a folder as a bag when it holds a
`metadata.yaml` (rosbag2 format version 5, storage `mcap`) listing the
storage files, their topics and message counts. The MCAP files themselves
already carry the schemas, so nothing else is needed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from shared.archive.reader import ArchiveReader, TopicInfo
from shared.errors import InputError
from shared.fsutil import write_text_atomic

ROSBAG2_METADATA_VERSION = 5


def _ns(value: int, key: str) -> dict[str, int]:
    return {key: int(value)}


def write_rosbag2_metadata(
    folder: Path | str,
    *,
    files: list[Path] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write `<folder>/metadata.yaml` describing the complete `*.mcap` files of `folder`.

    `files` picks the MCAP files (default: every `*.mcap` of the folder, by
    name; `.part` files are never complete and are left out). Returns the
    path written; OutputExistsError if it exists and `overwrite` is false;
    InputError when there is no MCAP file or a topic changes type between files.
    """
    root = Path(folder)
    mcap_files = sorted(root.glob("*.mcap")) if files is None else [Path(f) for f in files]
    if not mcap_files:
        raise InputError(f"{root}: no .mcap file to describe (expected recording*.mcap)")
    for path in mcap_files:
        if path.parent.resolve() != root.resolve():
            raise InputError(f"{path}: not inside {root} (rosbag2 files must be in the bag folder)")
    topics: dict[str, TopicInfo] = {}
    counts: dict[str, int] = {}
    file_entries: list[dict[str, Any]] = []
    for path in mcap_files:
        with ArchiveReader(path) as reader:
            file_topics = reader.topics()
        for name, info in file_topics.items():
            known = topics.get(name)
            if known is not None and known.schema_name != info.schema_name:
                raise InputError(
                    f"{path}: topic {name!r} holds {info.schema_name}, but "
                    f"{known.schema_name} in an earlier file"
                )
            topics.setdefault(name, info)
            counts[name] = counts.get(name, 0) + info.message_count
        count = sum(i.message_count for i in file_topics.values())
        first = min((i.first_log_time_ns for i in file_topics.values()), default=0)
        last = max((i.last_log_time_ns for i in file_topics.values()), default=0)
        file_entries.append(
            {
                "path": path.name,
                "starting_time": _ns(first, "nanoseconds_since_epoch"),
                "duration": _ns(last - first, "nanoseconds"),
                "message_count": count,
            }
        )
    counted = [f for f in file_entries if f["message_count"]]
    first = min((f["starting_time"]["nanoseconds_since_epoch"] for f in counted), default=0)
    last = max(
        (
            f["starting_time"]["nanoseconds_since_epoch"] + f["duration"]["nanoseconds"]
            for f in counted
        ),
        default=0,
    )
    information = {
        "version": ROSBAG2_METADATA_VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [f["path"] for f in file_entries],
        "duration": _ns(last - first, "nanoseconds"),
        "starting_time": _ns(first, "nanoseconds_since_epoch"),
        "message_count": sum(counts.values()),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": name,
                    "type": info.schema_name,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": "",
                },
                "message_count": counts[name],
            }
            for name, info in sorted(topics.items())
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": file_entries,
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": information}, sort_keys=False)
    return write_text_atomic(root / "metadata.yaml", text, overwrite=overwrite)
