"""Headless viewer clients for bench/bench_load.py: one process, many websocket clients.

Each reading client speaks viser's websocket protocol as the browser's client does
(viser/client/src/WebsocketInterface.tsx, MessageHandler.tsx): it connects with the
``viser-v<version>`` subprotocol, sends its camera once, and for every binary frame it
receives (``[8 B msgpack size][8 B compressed size][zstd msgpack][aligned buffers]``)
counts the bytes, decompresses the structure (not the binary buffers: a browser hands
those to WebGL as they are) and

- notes when the frame label (the timeline's ``frame **N**`` markdown, whose GUI uuid
  the bench passes) changes: which frame it holds and since when;
- answers each localStorage read (``LocalStorageGetItemRequestMessage``) as a page does
  from its render loop: the viewer's playback waits for these answers (mvviz.workers.
  PageAcks), so a client that did not answer would look like a stuck tab.

A stalled client is a raw socket that does the websocket handshake and never reads
again (a laptop closed mid-review, a client on a dead link); a mute client reads
everything and answers nothing (a browser tab in the background: the browser reads its
socket, the page does not draw, so it never answers).

The process is driven by JSON lines on stdin and answers with JSON lines on stdout::

    {"cmd": "connect", "n": 3}   -> {"ok": true, "ids": [0, 1, 2]}   (each has its replay)
    {"cmd": "connect", "n": 1, "mute": true}   (reads, never answers a localStorage read)
    {"cmd": "stall"}             -> {"ok": true}
    {"cmd": "mark"}              -> {"ok": true}   (counters restart)
    {"cmd": "report"}            -> {"clients": [{"id", "bytes", "frames", "closed",
                                     "dropped" (closed, not by us), "mute"}, ...]}
    {"cmd": "close", "ids": [..]}-> {"ok": true}
    {"cmd": "quit"}

``frames`` are ``[frame, time]`` pairs since the last mark (``time.monotonic()``, the
same clock as the server process's on Linux).

Usage (by bench_load.py): python -m bench.load_clients --url ws://HOST:PORT
    --label-uuid UUID --version VISER_VERSION
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import re
import socket
import sys
import time

import msgspec
import zstandard
from websockets.asyncio.client import connect

LABEL = re.compile(r"frame \*\*(\d+)\*\*")
CAMERA = {  # what a browser sends first: its camera (viser.ClientHandle.camera waits for it)
    "type": "ViewerCameraMessage",
    "wxyz": (1.0, 0.0, 0.0, 0.0),
    "position": (3.0, 3.0, 3.0),
    "fov": 0.87,
    "near": 0.01,
    "far": 1000.0,
    "image_height": 860,
    "image_width": 1400,
    "look_at": (0.0, 0.0, 0.0),
    "up_direction": (0.0, 0.0, 1.0),
}


class Client:
    """One reading client."""

    def __init__(
        self, cid: int, url: str, version: str, label_uuid: str, mute: bool = False
    ) -> None:
        self.id, self.url, self.version, self.label_uuid = cid, url, version, label_uuid
        self.mute = mute  # reads everything, answers nothing: a page that does not draw
        self.bytes = 0
        self.frames: list[tuple[int, float]] = []
        self.closed: str | None = None
        self.closing = False  # closed by us (not dropped)
        self.replayed = asyncio.Event()
        self._ws = None
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def close(self) -> None:
        self.closing = True
        if self._ws is not None:
            await self._ws.close()

    async def _run(self) -> None:
        dctx = zstandard.ZstdDecompressor()
        try:
            async with connect(
                self.url,
                subprotocols=[f"viser-v{self.version}"],
                max_size=None,
                compression=None,
                open_timeout=60,
            ) as ws:
                self._ws = ws
                await ws.send(msgspec.msgpack.encode(CAMERA))
                async for raw in ws:
                    self.bytes += len(raw)
                    await self._handle(ws, raw, dctx)
            self.closed = "closed"
        except Exception as exc:  # a disconnect is a figure, not a crash
            self.closed = f"{type(exc).__name__}: {exc}"
        finally:
            self.replayed.set()  # never leave connect() waiting

    async def _handle(self, ws, raw: bytes, dctx) -> None:
        inner_len = int.from_bytes(raw[:8], "little")
        comp_len = int.from_bytes(raw[8:16], "little")
        inner = dctx.decompress(raw[16 : 16 + comp_len], max_output_size=inner_len)
        for m in msgspec.msgpack.decode(inner)["messages"]:
            kind = m.get("type")
            if kind == "GuiUpdateMessage" and m.get("uuid") == self.label_uuid:
                u = m["updates"]
                found = LABEL.search(str(u.get("_markdown", u.get("content", ""))))
                if found:
                    self.frames.append((int(found.group(1)), time.monotonic()))
            elif kind == "LocalStorageGetItemRequestMessage" and not self.mute:
                answer = {
                    "type": "LocalStorageGetItemResponseMessage",
                    "value": None,
                    "error": None,
                    "request_uuid": m["request_uuid"],
                }
                await ws.send(msgspec.msgpack.encode(answer))
            elif kind == "ReplayDoneMessage":
                self.replayed.set()

    def report(self) -> dict:
        dropped = self.closed is not None and not self.closing
        return {"id": self.id, "bytes": self.bytes, "frames": self.frames,
                "closed": self.closed, "dropped": dropped, "mute": self.mute}  # fmt: skip


def stalled_socket(url: str, version: str) -> socket.socket:
    """A websocket handshake on a raw socket that is then never read."""
    host, port = url.removeprefix("ws://").split("/")[0].rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=30)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(
        (
            f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: viser-v{version}\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:  # the 101 answer; the first frames may follow it
        head += s.recv(1)
    if b" 101 " not in head.split(b"\r\n")[0]:
        raise RuntimeError(f"handshake refused: {head[:80]!r}")
    return s


async def serve(args: argparse.Namespace) -> None:
    loop = asyncio.get_running_loop()
    clients: list[Client] = []
    stalled: list[socket.socket] = []

    def answer(obj: dict) -> None:
        sys.stdout.write(json.dumps(obj) + "\n")
        sys.stdout.flush()

    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if not line:
            break
        cmd = json.loads(line)
        if cmd["cmd"] == "connect":
            mute = bool(cmd.get("mute", False))
            new = [Client(len(clients) + i, args.url, args.version, args.label_uuid, mute)
                   for i in range(cmd["n"])]  # fmt: skip
            for c in new:
                c.start()
            clients += new
            await asyncio.wait_for(asyncio.gather(*(c.replayed.wait() for c in new)), 120)
            answer({"ok": True, "ids": [c.id for c in new], "closed": [c.closed for c in new]})
        elif cmd["cmd"] == "stall":
            stalled.append(await loop.run_in_executor(None, stalled_socket, args.url, args.version))
            answer({"ok": True})
        elif cmd["cmd"] == "mark":
            for c in clients:
                c.bytes, c.frames = 0, []
            answer({"ok": True})
        elif cmd["cmd"] == "report":
            answer({"clients": [c.report() for c in clients]})
        elif cmd["cmd"] == "close":
            ids = set(cmd.get("ids", [c.id for c in clients]))
            await asyncio.gather(*(c.close() for c in clients if c.id in ids))
            for s in stalled if cmd.get("stalled", True) else ():
                s.close()
            answer({"ok": True})
        elif cmd["cmd"] == "quit":
            break
    for c in clients:
        await c.close()
    for s in stalled:
        s.close()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--url", required=True)
    ap.add_argument("--label-uuid", required=True)
    ap.add_argument("--version", required=True)
    asyncio.run(serve(ap.parse_args(argv)))


if __name__ == "__main__":
    main()
