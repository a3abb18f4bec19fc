"""A minimal client of the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``, the
messages of ``foxglove.websocket.v1``) for sim_node's live view: it reads the server's
``serverInfo`` and ``advertise`` messages, subscribes to some or all of the advertised
topics, and collects the binary ``messageData`` frames (opcode 0x01, subscription id u32
LE, log time u64 LE, payload) for a while. As a script it prints what it received, one line
per topic (message count, schema, first and last log time): the check that a live view
serves what it should, without a viewer.

    python -m starleth_sim.tools.view.live_log                 # ws://localhost:8765, 5 s
    python -m starleth_sim.tools.view.live_log --url ws://localhost:8765 --seconds 10 \
        /tf joint_states

Needs the ``websockets`` package (requirements-live.txt).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import struct
import sys
import time
from dataclasses import dataclass, field

from ...ros.live_view_front import LEGACY_SUBPROTOCOL, SUBPROTOCOL

OP_MESSAGE_DATA = 0x01


@dataclass
class LiveLog:
    """What a client received: the server's info, the advertised channels by topic
    ({topic: the advertise entry: id, encoding, schemaName, schemaEncoding, schema}) and
    the messages of each subscribed topic, [(log time ns, payload bytes)]."""

    server_info: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)
    messages: dict = field(default_factory=dict)

    def summary_lines(self) -> list:
        """One line per advertised topic: messages, schema, first / last log time."""
        lines = [f"server {self.server_info.get('name', '?')!r}, "
                 f"{len(self.channels)} topics advertised"]
        for topic in sorted(self.channels):
            ch, msgs = self.channels[topic], self.messages.get(topic, [])
            times = (f"log time {msgs[0][0] * 1e-9:.4f} .. {msgs[-1][0] * 1e-9:.4f} s"
                     if msgs else "")
            lines.append(f"  {topic:34s} {ch['schemaName']:34s} {len(msgs):6d} msgs  {times}")
        return lines


def _matches(topic, wanted) -> bool:
    """`topic` (resolved) is one of `wanted` (resolved names or relative ones: a suffix)."""
    return any(topic == w or (not w.startswith("/") and topic.endswith("/" + w))
               for w in wanted)


async def collect_async(url, topics=None, seconds=5.0, until=None, connect_timeout=30.0,
                        subprotocol=SUBPROTOCOL):
    """Connect to `url` offering `subprotocol`, subscribe to `topics` (None: every
    advertised one; relative names match any namespace) as soon as they are advertised,
    and collect for `seconds` after the connection (or until ``until(log)`` is true).
    Retries the connection until connect_timeout (a server still starting)."""
    import websockets  # optional dependency: requirements-live.txt

    log = LiveLog()
    deadline = time.monotonic() + connect_timeout
    while True:
        try:
            ws = await websockets.connect(url, subprotocols=[subprotocol], max_size=None)
            break
        except (OSError, websockets.exceptions.InvalidHandshake):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    by_sub, next_id = {}, 1
    end = time.monotonic() + seconds
    async with ws:
        while time.monotonic() < end and not (until is not None and until(log)):
            try:      # (at most 0.5 s: `until` is looked at while nothing arrives too)
                m = await asyncio.wait_for(ws.recv(),
                                           timeout=min(0.5, max(0.01, end - time.monotonic())))
            except asyncio.TimeoutError:
                continue
            except websockets.exceptions.ConnectionClosed:   # the server stopped
                break
            if isinstance(m, bytes):
                if m[0] == OP_MESSAGE_DATA:
                    sub, t = struct.unpack_from("<IQ", m, 1)
                    topic = by_sub.get(sub)
                    if topic is not None:
                        log.messages.setdefault(topic, []).append((t, m[13:]))
                continue
            op = json.loads(m)
            if op.get("op") == "serverInfo":
                log.server_info = op
            elif op.get("op") == "advertise":
                subs = []
                for ch in op["channels"]:
                    log.channels[ch["topic"]] = ch
                    if topics is None or _matches(ch["topic"], topics):
                        by_sub[next_id] = ch["topic"]
                        subs.append({"id": next_id, "channelId": ch["id"]})
                        next_id += 1
                if subs:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
    return log


def collect(url, topics=None, seconds=5.0, until=None, connect_timeout=30.0,
            subprotocol=SUBPROTOCOL) -> LiveLog:
    """collect_async, run to its end."""
    return asyncio.run(collect_async(url, topics, seconds, until, connect_timeout,
                                     subprotocol))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m starleth_sim.tools.view.live_log",
                                 description="Log what sim_node's live view serves.")
    ap.add_argument("topics", nargs="*", help="topics to subscribe to (default: all)")
    ap.add_argument("--url", default="ws://localhost:8765")
    ap.add_argument("--seconds", type=float, default=5.0, help="how long to listen")
    ap.add_argument("--connect-timeout", type=float, default=60.0,
                    help="seconds to keep trying to connect (a node still starting)")
    ap.add_argument("--subprotocol", default=SUBPROTOCOL,
                    choices=(SUBPROTOCOL, LEGACY_SUBPROTOCOL),
                    help="the name of the protocol to offer (the older one as clients "
                         "before 2025 do)")
    args = ap.parse_args(argv)
    try:
        log = collect(args.url, args.topics or None, args.seconds,
                      connect_timeout=args.connect_timeout, subprotocol=args.subprotocol)
    except ImportError:
        print("live_log: the websockets package is missing: pip install -r "
              "requirements-live.txt", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"live_log: cannot connect to {args.url}: {e}", file=sys.stderr)
        return 1
    print("\n".join(log.summary_lines()))
    return 0 if any(log.messages.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
