#!/usr/bin/env python3
"""The complete view sets of an MCAP log per the reference Python reader, CRCs checked.

A set is complete when its capture events name every one of its views. Prints one JSON line:
the complete set indices, the chunk count, metadata and attachment names. Exit 1 when the
reader rejects the file. Used by the crash-safety tests and scripts/truncation-sweep.py.
"""
import json
import sys
from collections import defaultdict

from mcap.reader import make_reader


def complete_sets(path):
    """(complete set indices, chunk count, metadata names, attachment names)."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        views, expected = defaultdict(set), {}
        for _, _, message in reader.iter_messages(topics=["/capture/events"]):
            event = json.loads(message.data)
            views[event["set_index"]].add(event["role"])
            expected[event["set_index"]] = event["views_in_set"]
        metadata = sorted(m.name for m in reader.iter_metadata())
        attachments = sorted(a.name for a in reader.iter_attachments())
    complete = sorted(i for i in views if len(views[i]) == expected[i])
    return complete, len(summary.chunk_indexes), metadata, attachments


if __name__ == "__main__":
    complete, chunks, metadata, attachments = complete_sets(sys.argv[1])
    print(json.dumps({"complete": complete, "chunks": chunks, "metadata": metadata, "attachments": attachments}))
