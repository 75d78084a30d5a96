#!/usr/bin/env python3
"""Independent check of sunjitter MCAP logs with the official Python `mcap` reader.

Checks every file (directories: every *.mcap in them) against contract.md's "MCAP layout":
  - a finished file: summary with statistics, zstd chunks each with a message index;
  - the metadata record `sunjitter` with `version` and `config` (a JSON document);
  - topics and schemas: /jitter/<channel> -> sunjitter.FrameAlignment,
    /reference/<channel> -> sunjitter.ReferenceChange, /log -> foxglove.Log, /alert ->
    sunjitter.Alert; schema encoding
    `jsonschema`, message encoding `json`; no other topic;
  - every schema loads in Foxglove: its JSON Schema parser takes one `type` per field (or a
    `oneOf` of numeric consts), so nullable fields are `"nullable": true` (OpenAPI style);
  - every message is JSON and valid against its channel's JSON Schema, `nullable` fields also
    accepting null (with the `jsonschema` package; without it, only the schema's `required`
    keys are checked, and a line says so);
  - /jitter: log_time equals the message's obs_time (ISO 8601 UTC) within --time-tolerance-ns;
    /log: log_time equals the foxglove timestamp;
  - file names `sunjitter-YYYYMMDDTHHMMSSZ-NNNN.mcap` (for files named sunjitter-*).
Expectations: --expect-topic TOPIC (present), --expect-count TOPIC=N (messages over all files).

Exit status 0 when everything holds, 1 on any mismatch (each printed on stderr), 2 on usage.

CI (.ci/run), after `pip install mcap zstandard jsonschema`:
    cargo test --test mcap_sink writes_fixture_for_the_python_reader_check
    python3 tools/check_mcap.py target/tmp/mcap_sink_fixture \
        --expect-count /jitter/SJI_1400=26 --expect-count /jitter/SJI_2796=20 \
        --expect-count /reference/SJI_1400=1 --expect-count /log=1
"""

import argparse
import json
import re
import sys
from pathlib import Path

try:
    from mcap.reader import make_reader
except ImportError:  # pragma: no cover - reported, never a silent pass
    print("check_mcap: the Python 'mcap' package is not installed (pip install mcap zstandard)",
          file=sys.stderr)
    sys.exit(2)

try:
    import jsonschema
except ImportError:
    jsonschema = None

SCHEMA_FOR = [
    (re.compile(r"^/jitter/[^/]+$"), "sunjitter.FrameAlignment"),
    (re.compile(r"^/reference/[^/]+$"), "sunjitter.ReferenceChange"),
    (re.compile(r"^/log$"), "foxglove.Log"),
    (re.compile(r"^/alert$"), "sunjitter.Alert"),
]
NAME = re.compile(r"^sunjitter-\d{8}T\d{6}Z-\d{4,}\.mcap$")
ISO = re.compile(r"^(\d{4})-(\d{2})-(\d{2})T(\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?(Z|[+-]00:?00)?$")


def iso_to_ns(text):
    """ISO 8601 UTC to ns since the epoch, keeping up to 9 fractional digits."""
    import calendar

    m = ISO.match(text)
    if not m:
        raise ValueError(f"not ISO 8601 UTC: {text!r}")
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    frac = (m.group(7) or "").ljust(9, "0")
    secs = calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0))
    return secs * 1_000_000_000 + int(frac or 0)


def foxglove_problems(schema, path):
    """What Foxglove's JSON Schema parser (studio parseJsonSchema.ts) would reject."""
    if schema.get("type") != "object":
        return [f"{path}: type must be \"object\", got {schema.get('type')!r}"]
    out = []
    for name, field in (schema.get("properties") or {}).items():
        here = f"{path}.{name}"
        if isinstance(field.get("oneOf"), list):
            if not all(isinstance(a.get("const"), (int, float)) for a in field["oneOf"]):
                out.append(f"{here}: oneOf alternatives must be numeric consts")
            continue
        t = field.get("type")
        if t in ("boolean", "number", "integer"):
            pass
        elif t == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                out.append(f"{here}: contentEncoding {field['contentEncoding']!r}")
        elif t == "object":
            out.extend(foxglove_problems(field, here))
        elif t == "array":
            it = (field.get("items") or {}).get("type")
            if it == "object":
                out.extend(foxglove_problems(field["items"], here))
            elif it not in ("boolean", "string", "number", "integer"):
                out.append(f"{here}: array items of type {it!r}")
        else:
            out.append(f"{here}: unsupported type {t!r} (Foxglove takes a single type)")
    return out


def widen_nullable(node):
    """A copy of a schema where `"nullable": true` fields also accept null."""
    if isinstance(node, dict):
        out = {k: widen_nullable(v) for k, v in node.items()}
        if out.get("nullable") is True and isinstance(out.get("type"), str):
            out["type"] = [out["type"], "null"]
        return out
    if isinstance(node, list):
        return [widen_nullable(v) for v in node]
    return node


class Checker:
    def __init__(self, tolerance_ns):
        self.problems = []
        self.counts = {}
        self.tolerance_ns = tolerance_ns
        self.validators = {}

    def fail(self, path, text):
        self.problems.append(f"{path}: {text}")

    def validator(self, schema):
        key = (schema.id, schema.name, schema.data)
        if key not in self.validators:
            doc = widen_nullable(json.loads(schema.data))
            if jsonschema is not None:
                cls = jsonschema.validators.validator_for(doc)
                cls.check_schema(doc)
                self.validators[key] = ("jsonschema", cls(doc))
            else:
                self.validators[key] = ("required", doc.get("required", []))
        return self.validators[key]

    def check_file(self, path):
        if path.name.startswith("sunjitter-") and not NAME.match(path.name):
            self.fail(path, "segment name is not sunjitter-YYYYMMDDTHHMMSSZ-NNNN.mcap")
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                self.fail(path, "no summary section: unfinished segment (recover it first)")
                return
            if summary.statistics is None:
                self.fail(path, "no statistics record in the summary")
            if not summary.chunk_indexes:
                self.fail(path, "no chunk indexes (not chunked?)")
            for ci in summary.chunk_indexes:
                if ci.compression != "zstd":
                    self.fail(path, f"chunk at {ci.chunk_start_offset} compression "
                                    f"{ci.compression!r}, expected 'zstd'")
                if ci.message_end_time >= ci.message_start_time and not ci.message_index_offsets:
                    self.fail(path, f"chunk at {ci.chunk_start_offset} has no message index")

            for channel in summary.channels.values():
                schema = summary.schemas.get(channel.schema_id)
                expected = next((s for rx, s in SCHEMA_FOR if rx.match(channel.topic)), None)
                if expected is None:
                    self.fail(path, f"unexpected topic {channel.topic!r}")
                if schema is None:
                    self.fail(path, f"{channel.topic}: no schema")
                    continue
                if expected is not None and schema.name != expected:
                    self.fail(path, f"{channel.topic}: schema {schema.name!r}, expected {expected!r}")
                if schema.encoding != "jsonschema":
                    self.fail(path, f"{channel.topic}: schema encoding {schema.encoding!r}")
                if channel.message_encoding != "json":
                    self.fail(path, f"{channel.topic}: message encoding {channel.message_encoding!r}")
                try:
                    for p in foxglove_problems(json.loads(schema.data), schema.name):
                        self.fail(path, f"{channel.topic}: Foxglove cannot load the schema: {p}")
                except ValueError as e:
                    self.fail(path, f"{channel.topic}: schema is not JSON: {e}")

            metas = [m for m in reader.iter_metadata() if m.name == "sunjitter"]
            if not metas:
                self.fail(path, "no 'sunjitter' metadata record")
            for m in metas:
                if not m.metadata.get("version"):
                    self.fail(path, "metadata 'sunjitter' has no version")
                try:
                    json.loads(m.metadata.get("config", ""))
                except ValueError as e:
                    self.fail(path, f"metadata 'sunjitter' config is not JSON: {e}")

            n = 0
            for schema, channel, message in reader.iter_messages():
                n += 1
                self.counts[channel.topic] = self.counts.get(channel.topic, 0) + 1
                where = f"{channel.topic} message at log_time {message.log_time}"
                try:
                    doc = json.loads(message.data)
                except ValueError as e:
                    self.fail(path, f"{where}: not JSON: {e}")
                    continue
                kind, v = self.validator(schema)
                if kind == "jsonschema":
                    errors = sorted(v.iter_errors(doc), key=str)
                    if errors:
                        self.fail(path, f"{where}: {errors[0].message} (at {list(errors[0].path)})")
                else:
                    missing = [k for k in v if k not in doc]
                    if missing:
                        self.fail(path, f"{where}: missing {missing}")
                if schema.name == "sunjitter.FrameAlignment":
                    try:
                        obs = iso_to_ns(doc.get("obs_time", ""))
                        if abs(obs - message.log_time) > self.tolerance_ns:
                            self.fail(path, f"{where}: log_time != obs_time {doc['obs_time']}")
                    except ValueError as e:
                        self.fail(path, f"{where}: {e}")
                elif schema.name == "foxglove.Log":
                    ts = doc.get("timestamp", {})
                    if ts.get("sec", 0) * 1_000_000_000 + ts.get("nsec", 0) != message.log_time:
                        self.fail(path, f"{where}: log_time != timestamp {ts}")
            stats = summary.statistics
            if stats is not None and stats.message_count != n:
                self.fail(path, f"statistics say {stats.message_count} messages, read {n}")
            print(f"{path}: {n} messages, {len(summary.chunk_indexes)} chunks, "
                  f"{len(summary.channels)} channels")


def files_of(paths):
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            out.extend(sorted(q for q in p.iterdir() if q.suffix == ".mcap" and q.is_file()))
        elif p.is_file():
            out.append(p)
        else:
            print(f"check_mcap: {p}: no such file or directory", file=sys.stderr)
            sys.exit(2)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("paths", nargs="+", help="MCAP files or directories")
    ap.add_argument("--expect-topic", action="append", default=[], metavar="TOPIC")
    ap.add_argument("--expect-count", action="append", default=[], metavar="TOPIC=N")
    ap.add_argument("--time-tolerance-ns", type=int, default=1_000_000,
                    help="allowed |log_time - obs_time| (default 1 ms: DATE-OBS precision)")
    args = ap.parse_args()

    expected_counts = {}
    for item in args.expect_count:
        topic, sep, n = item.rpartition("=")
        if not sep or not topic or not n.isdigit():
            print(f"check_mcap: --expect-count wants TOPIC=N, got {item!r}", file=sys.stderr)
            sys.exit(2)
        expected_counts[topic] = int(n)

    files = files_of(args.paths)
    if not files:
        print("check_mcap: no .mcap files given", file=sys.stderr)
        sys.exit(1)
    if jsonschema is None:
        print("check_mcap: 'jsonschema' not installed: checking required keys only "
              "(pip install jsonschema for full validation)")
    checker = Checker(args.time_tolerance_ns)
    for path in files:
        try:
            checker.check_file(path)
        except Exception as e:  # the official reader refused the file
            checker.fail(path, f"unreadable by the mcap reader: {type(e).__name__}: {e}")
    for topic in args.expect_topic:
        if topic not in checker.counts:
            checker.problems.append(f"topic {topic} not found")
    for topic, n in expected_counts.items():
        got = checker.counts.get(topic, 0)
        if got != n:
            checker.problems.append(f"topic {topic}: {got} messages, expected {n}")
    for topic, n in sorted(checker.counts.items()):
        print(f"  {topic}: {n}")
    if checker.problems:
        for p in checker.problems:
            print(f"check_mcap: {p}", file=sys.stderr)
        print(f"check_mcap: FAILED ({len(checker.problems)} problems)", file=sys.stderr)
        sys.exit(1)
    print(f"check_mcap: OK ({len(files)} files)")


if __name__ == "__main__":
    main()
