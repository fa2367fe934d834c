"""The Foxglove live view, end to end over its WebSocket, on 127.0.0.1.

A client written here (the handshake and frames of RFC 6455, the Foxglove WebSocket
protocol's JSON ops) connects as Foxglove would: it is told the server and its channels
(the well-known schemas), subscribes to the status, and gets the core's mode in the
messages the daemon's hooks publish, no faster than the configured rate. Nobody
watching: nothing is encoded at all. Only loopback unless the vehicle file says so.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import socket
import struct
import time
from typing import Any

import pytest

from appliance.config import load_config
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.live_view import LiveView, RateGate, check_host
from tests.runtime.inline import free_port


class WsClient:
    """Just enough of a WebSocket client for the Foxglove protocol."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        self.buffer = b""
        while b"\r\n\r\n" not in self.buffer:
            self.buffer += self._recv()
        head, _, self.buffer = self.buffer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 101"), head

    def _recv(self) -> bytes:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection")
        return chunk

    def _need(self, n: int) -> bytes:
        while len(self.buffer) < n:
            self.buffer += self._recv()
        data, self.buffer = self.buffer[:n], self.buffer[n:]
        return data

    def frame(self) -> tuple[int, bytes]:
        first, second = self._need(2)
        length = second & 0x7F
        if length == 126:
            (length,) = struct.unpack(">H", self._need(2))
        elif length == 127:
            (length,) = struct.unpack(">Q", self._need(8))
        return first & 0x0F, self._need(length)

    def send_json(self, obj: Any) -> None:
        payload = json.dumps(obj).encode()
        mask = os.urandom(4)
        header = bytes([0x81])
        n = len(payload)
        header += bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(header + mask + masked)

    def close(self) -> None:
        self.sock.close()


def _live_view_config(port: int) -> Any:
    config = load_config("flatbed")
    return config.model_copy(
        update={"live_view": config.live_view.model_copy(update={"enabled": True, "port": port})}
    )


class _Ctx:
    name = "live_view"

    def beat(self) -> None:
        pass


def test_only_loopback_unless_the_vehicle_file_allows_more() -> None:
    assert check_host("127.0.0.1", False) == "127.0.0.1"
    assert check_host("::1", False) == "::1"
    with pytest.raises(ValueError, match="not a loopback address"):
        check_host("0.0.0.0", False)
    with pytest.raises(ValueError, match="not a loopback address"):
        check_host("192.168.1.10", False)
    assert check_host("192.168.1.10", True) == "192.168.1.10"
    with pytest.raises(ValueError, match="not an IP address"):
        check_host("example.com", True)


def test_the_rate_gate_passes_one_per_interval_per_key() -> None:
    gate = RateGate(10.0)
    passed = [t for t in (i * 0.01 for i in range(100)) if gate.update("a", t)]
    assert len(passed) == 10
    assert gate.update("b", 0.99)  # another topic has its own budget


def test_nobody_watching_costs_no_encoding() -> None:
    view = LiveView(_live_view_config(free_port()), 0)
    core = ControlCore(load_config("flatbed"), None)
    inputs = ControlInputs(ages_s={})
    for i in range(50):
        view.on_cycle(i * 0.02, inputs, core.step(inputs, i * 0.02))
    assert view.published == 0


def test_foxglove_sees_the_channels_and_the_mode_no_faster_than_the_rate() -> None:
    port = free_port()
    view = LiveView(_live_view_config(port), 0)
    core = ControlCore(load_config("flatbed"), None)

    async def scenario() -> list[dict[str, Any]]:
        service = asyncio.ensure_future(view.run(_Ctx()))  # type: ignore[arg-type]
        try:
            for _ in range(200):
                if view.bound_port is not None:
                    break
                await asyncio.sleep(0.01)
            client = await asyncio.to_thread(WsClient, port)
            try:
                info = json.loads((await asyncio.to_thread(client.frame))[1])
                assert info["op"] == "serverInfo"
                channels: dict[str, dict[str, Any]] = {}
                while "/dbw/status" not in channels:
                    op = json.loads((await asyncio.to_thread(client.frame))[1])
                    if op["op"] == "advertise":
                        channels.update({c["topic"]: c for c in op["channels"]})
                assert channels["/scan/left"]["schemaName"] == "foxglove.LaserScan"
                assert channels["/dbw/pose"]["schemaName"] == "foxglove.PoseInFrame"
                assert channels["/log"]["schemaName"] == "foxglove.Log"
                await asyncio.to_thread(
                    client.send_json,
                    {
                        "op": "subscribe",
                        "subscriptions": [{"id": 7, "channelId": channels["/dbw/status"]["id"]}],
                    },
                )
                for _ in range(200):  # the subscription reaches the server's threads
                    if view.status.has_sinks():
                        break
                    await asyncio.sleep(0.01)
                assert view.status.has_sinks()
                inputs = ControlInputs(ages_s={})
                for i in range(100):  # one second of cycles at 100 Hz
                    now_s = 10.0 + i * 0.01
                    view.on_cycle(now_s, inputs, core.step(inputs, now_s))
                messages: list[dict[str, Any]] = []
                deadline = time.monotonic() + 5.0
                while len(messages) < view.published and time.monotonic() < deadline:
                    opcode, data = await asyncio.to_thread(client.frame)
                    if opcode == 0x2 and data[0] == 0x01:  # binary: message data
                        (sub_id,) = struct.unpack_from("<I", data, 1)
                        assert sub_id == 7
                        messages.append(json.loads(data[13:]))
                return messages
            finally:
                client.close()
        finally:
            service.cancel()
            await asyncio.gather(service, return_exceptions=True)

    messages = asyncio.run(scenario())
    assert 9 <= len(messages) <= 11  # 10 Hz of a 100 Hz loop
    assert all(m["mode"] in {"boot", "self_check"} for m in messages)
    assert messages[-1]["commands"]["steering"] == "released"


def test_the_route_near_the_vehicle_is_a_line_in_the_enu_frame() -> None:
    """The route source's window becomes one SceneUpdate entity (id ``route``, replaced on
    each update) in the ``enu`` frame, its points in order: read from the message's own
    protobuf encoding (the SDK's objects expose no fields), where each coordinate is a
    little-endian double."""
    points = [[1.0, 2.0], [3.5, 4.0], [6.0, 6.5]]
    encoded = LiveView.route_scene({"points_m": points}, 12).encode()
    assert b"enu" in encoded and b"route" in encoded
    at = [encoded.index(struct.pack("<d", value)) for point in points for value in point[1:]]
    assert at == sorted(at)  # the points in the route's order
    for east, _ in points[1:]:
        assert struct.pack("<d", east) in encoded
    assert b"route" in LiveView.route_scene({"points_m": []}, 12).encode()
    view = LiveView(_live_view_config(free_port()), 0)
    assert view.route.topic() == "/dbw/route" and view.gnss_pose.topic() == "/dbw/gnss_pose"
