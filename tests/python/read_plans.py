"""Reads the plans of an adaptive capture with the reference Python `mcap` reader (CRCs checked):
prints how many `/capture/plan` messages there are; each must be JSON with candidates and a choice."""
import json
import sys

from mcap.reader import make_reader

with open(sys.argv[1], "rb") as f:
    reader = make_reader(f, validate_crcs=True)
    count = 0
    for schema, channel, message in reader.iter_messages(topics=["/capture/plan"]):
        assert schema.name == "multiscopic.CapturePlan", schema.name
        plan = json.loads(message.data)
        assert plan["candidates"] and "chosen_offset" in plan, plan
        count += 1
print(f"{count} plans")
