#!/usr/bin/env python3
"""Reads an MCAP log with the reference Python clients (`mcap`, `mcap-protobuf-support`).

Checks the CRCs of every chunk and of the data and summary sections, decodes every message of
every channel (protobuf through its embedded descriptor, JSON through json.loads), and checks
that the statistics agree with what was read. Prints one JSON line with per-topic counts.
Exit 0 when everything decodes, 1 otherwise.
"""
import json
import sys
from collections import Counter

from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


class JsonDecoderFactory(McapDecoderFactory):
    """Decodes `json` channels (our capture events) with the standard library."""

    def decoder_for(self, message_encoding, schema):
        if message_encoding == "json":
            return lambda data: json.loads(data)
        return None


def main(path):
    counts = Counter()
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True, decoder_factories=[DecoderFactory(), JsonDecoderFactory()])
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            print(f"{path}: no summary or statistics section", file=sys.stderr)
            return 1
        header = reader.get_header()
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            if decoded is None:
                print(f"{channel.topic}: message did not decode", file=sys.stderr)
                return 1
            counts[channel.topic] += 1
        expected = {
            summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()
        }
        if dict(counts) != expected:
            print(f"decoded counts {dict(counts)} differ from statistics {expected}", file=sys.stderr)
            return 1
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = [a.name for a in reader.iter_attachments()]
    # A second pass over the data section alone (no summary) re-checks the chunk CRCs on a linear scan.
    with open(path, "rb") as stream:
        from mcap.stream_reader import StreamReader
        records = sum(1 for _ in StreamReader(stream, validate_crcs=True).records)
    print(json.dumps({
        "profile": header.profile,
        "library": header.library,
        "messages": sum(counts.values()),
        "topics": dict(sorted(counts.items())),
        "schemas": sorted({s.name for s in summary.schemas.values()}),
        "metadata": sorted(metadata),
        "attachments": attachments,
        "chunks": len(summary.chunk_indexes),
        "records": records,
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
