#!/usr/bin/env python3
"""A simulated log as a real camera on the arm would log it: the same images, calibrations,
poses, arm states, metadata and attachments, without the ground truth.

Leaves out every `/camera/*/ground_truth/*` topic and, in each capture event, the ground-truth
topics and the true camera pose (`depth_topic`, `surface_topic`, `true_world_from_camera`
become null). `replay` then runs the methods and writes their results but has nothing to
evaluate against: the process a workcell runs (`scripts/bench-replay.py` with TRUTH=0).
Chunks of 4 MiB, zstd, as `record` writes them.

Usage: .venv/bin/python scripts/strip-truth.py IN.mcap OUT.mcap
  (the `mcap` package: pip install -r tests/python/requirements.txt into the venv)
"""
import json
import sys

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

EVENTS_TOPIC = "/capture/events"
TRUTH_FIELDS = ("depth_topic", "surface_topic", "true_world_from_camera")


def strip(source, destination):
    """Copies `source` to `destination` without the ground truth; returns the messages left out."""
    left_out = 0
    with open(source, "rb") as inp, open(destination, "wb") as out:
        reader = make_reader(inp)
        summary = reader.get_summary()
        if summary is None:
            raise SystemExit(f"{source}: no summary (a cut log: `replay recover` it first)")
        header = reader.get_header()
        writer = Writer(out, chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        schemas = {
            sid: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data)
            for sid, s in summary.schemas.items()
        }
        channels = {}
        for cid, channel in summary.channels.items():
            if "/ground_truth/" in channel.topic:
                continue
            channels[cid] = writer.register_channel(
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_id=schemas.get(channel.schema_id, 0),
                metadata=dict(channel.metadata),
            )
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        for attachment in reader.iter_attachments():
            writer.add_attachment(
                attachment.create_time, attachment.log_time, attachment.name, attachment.media_type, attachment.data
            )
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if channel.id not in channels:
                left_out += 1
                continue
            data = message.data
            if channel.topic == EVENTS_TOPIC:
                event = json.loads(data)
                for field in TRUTH_FIELDS:
                    if field in event:
                        event[field] = None
                data = json.dumps(event).encode()
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()
    return left_out


def main():
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    left_out = strip(sys.argv[1], sys.argv[2])
    print(f"{sys.argv[2]}: {left_out} ground-truth messages left out")


if __name__ == "__main__":
    main()
