#!/usr/bin/env python3
"""Truncation sweep of any log: cuts it at every STEP bytes and at every byte within WINDOW of each
chunk's end, and checks that `replay check` keeps exactly the sets completed before the cut (a set
is complete when every chunk holding messages of its views' times ends before the cut), exits 3
and never panics; every RECOVER_EVERY-th cut (and every cut at a chunk's end) is also passed through
`replay recover`, and the result read by the reference Python `mcap` reader with CRCs checked.

Usage: .venv/bin/python scripts/truncation-sweep.py LOG [--step 4096] [--window 64] [--recover-every 16]
Prints one JSON line per failure and a summary line; exit 1 when any cut failed.
"""
import argparse, json, os, subprocess, sys, tempfile, time
from collections import defaultdict

from mcap.reader import make_reader

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "python"))
from complete_sets import complete_sets  # noqa: E402  (the tests' reference reader)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log")
    parser.add_argument("--step", type=int, default=4096)
    parser.add_argument("--window", type=int, default=64)
    parser.add_argument("--recover-every", type=int, default=16)
    parser.add_argument("--replay", default="target/release/replay")
    args = parser.parse_args()
    data = open(args.log, "rb").read()
    with open(args.log, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        chunks = sorted((c.chunk_start_offset + c.chunk_length, c.message_start_time, c.message_end_time)
                        for c in summary.chunk_indexes)
        times = defaultdict(list)
        for _, _, message in reader.iter_messages(topics=["/capture/events"]):
            event = json.loads(message.data)
            times[event["set_index"]].append(event["capture_time_nanos"])
    # The offset from which each set is whole: the end of the last chunk overlapping its views' times.
    set_end = {k: max(end for end, start, stop in chunks if start <= max(t) and stop >= min(t)) for k, t in times.items()}
    ends = [end for end, _, _ in chunks]
    cuts = set(range(args.step, len(data), args.step))
    for end in ends:
        cuts.update(range(max(1, end - args.window), min(len(data), end + args.window + 1)))
    cuts = sorted(cuts)
    failures, recovered = 0, 0
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        cut_path, fixed_path = os.path.join(tmp, "cut.mcap"), os.path.join(tmp, "fixed.mcap")
        for n, cut in enumerate(cuts):
            with open(cut_path, "wb") as f:
                f.write(data[:cut])
            want = sorted(k for k, end in set_end.items() if end <= cut)
            check = subprocess.run([args.replay, "check", cut_path, "--json", "-q"], capture_output=True)
            got = sorted(s["set"] for s in json.loads(check.stdout or b"[]")) if check.returncode in (0, 3) else None
            problem = None
            if check.returncode != 3 or got != want:
                problem = {"cut": cut, "exit": check.returncode, "sets": got, "expected": want,
                           "stderr": check.stderr.decode(errors="replace")[-300:]}
            elif n % args.recover_every == 0 or cut in ends:
                recover = subprocess.run([args.replay, "recover", cut_path, "-o", fixed_path, "-q"], capture_output=True)
                recovered += 1
                try:
                    sets = complete_sets(fixed_path)[0] if recover.returncode in (0, 3) else None
                except Exception as error:  # the reference reader rejected the file
                    sets = f"python mcap: {error}"
                if sets != want:
                    problem = {"cut": cut, "recover_exit": recover.returncode, "recovered_sets": sets, "expected": want}
            if problem:
                failures += 1
                print(json.dumps(problem))
    print(json.dumps({"log": args.log, "bytes": len(data), "chunks": len(chunks), "sets": len(set_end),
                      "cuts": len(cuts), "recovered": recovered, "failures": failures,
                      "seconds": round(time.time() - started, 1)}))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
