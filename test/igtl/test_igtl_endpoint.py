"""The non-blocking OpenIGTLink server and client over real loopback sockets (no ROS)."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time

import numpy as np
import pytest
from igtl_support import (
    Recorder,
    SlicerServerStandIn,
    assert_wire_equal,
    expected_transform,
    free_port,
    hung_up,
    pyigtl,
)

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.endpoint import IgtlClient, IgtlServer
from liver_p2p_reg.slicer_config import SlicerConfig


@pytest.fixture
def bridge():
    config = SlicerConfig(host="127.0.0.1", port=0, max_queue_messages=4, max_queue_mb=1.0)
    endpoint = open_endpoint(config)
    yield SlicerBridge(config, endpoint)
    endpoint.close()


def pose(x_mm: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x_mm, 2.0, 3.0]
    return T


def test_late_joiner_gets_the_current_model_pose_and_status(bridge: SlicerBridge) -> None:
    model = np.random.default_rng(0).uniform(-80, 80, (500, 3))
    bridge.send_model(model, stamp_ns=1)
    bridge.send_pose(pose(1.0), 2)
    bridge.send_pose(pose(7.0), 3)
    bridge.send_status("WARN", "registered: residual 5.0 mm", 3)
    late = Recorder.connect(bridge.endpoint.port)
    try:
        polydata = late.wait_for("PreopModel")[0].value
        assert len(polydata.polygons) == 500  # one small triangle per point
        np.testing.assert_allclose(polydata.points[:500], (model * [-1, -1, 1]).astype(np.float32), atol=0)
        transforms = late.wait_for("CTToSensor")
        assert len(transforms) == 1  # the latest state only, not the history
        assert_wire_equal(transforms[0].value, expected_transform(pose(7.0)))
        assert late.wait_for("RegistrationStatus")[0].value == "WARN: registered: residual 5.0 mm"
    finally:
        late.close()


def test_reconnecting_client_gets_the_state_then_the_stream(bridge: SlicerBridge) -> None:
    bridge.send_pose(pose(1.0), 1)
    first = Recorder.connect(bridge.endpoint.port)
    first.wait_for("CTToSensor")
    first.close()
    assert bridge.endpoint.flush(5.0)
    deadline = time.monotonic() + 5
    while bridge.endpoint.peer_count() and time.monotonic() < deadline:  # the server notices the close
        bridge.send_status("OK", "tick")
        time.sleep(0.05)
    assert bridge.endpoint.peer_count() == 0
    bridge.send_pose(pose(2.0), 2)
    again = Recorder.connect(bridge.endpoint.port)
    try:
        assert_wire_equal(again.wait_for("CTToSensor")[0].value, expected_transform(pose(2.0)))
        bridge.send_pose(pose(3.0), 3)
        assert_wire_equal(again.wait_for("CTToSensor", 2)[1].value, expected_transform(pose(3.0)))
        assert bridge.endpoint.stats()["connections"] == 2
    finally:
        again.close()


def test_stock_pyigtl_client_receives_transform_and_status(bridge: SlicerBridge) -> None:
    client = pyigtl.OpenIGTLinkClient("127.0.0.1", bridge.endpoint.port)
    try:
        assert bridge.endpoint.wait_for_peers(1, 10.0)
        bridge.send_model(np.random.default_rng(1).uniform(-50, 50, (100, 3)))  # pyigtl skips POLYDATA
        bridge.send_pose(pose(4.0), 4)
        bridge.send_status("OK", "registered: residual 1.00 mm", 4)
        message = client.wait_for_message("CTToSensor", timeout=10)
        assert_wire_equal(message.matrix, expected_transform(pose(4.0)))
        assert client.wait_for_message("RegistrationStatus", timeout=10).string.startswith("OK: registered")
    finally:
        client.stop()


def test_garbage_disconnects_only_that_client(bridge: SlicerBridge) -> None:
    good = Recorder.connect(bridge.endpoint.port)
    try:
        good.wait_for("CTToSensor", 0)
        # A valid message from a client (Slicer may send its own) is read and ignored.
        polite = socket.create_connection(("127.0.0.1", bridge.endpoint.port))
        polite.sendall(pyigtl.StringMessage("hello", device_name="Slicer").pack())
        cases = [os.urandom(4096), b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + b"\0" * 64]
        for garbage in cases:
            rude = socket.create_connection(("127.0.0.1", bridge.endpoint.port), timeout=10)
            rude.sendall(garbage)
            assert hung_up(rude)
            rude.close()
        assert bridge.endpoint.stats()["garbage_disconnections"] == len(cases)
        bridge.send_pose(pose(5.0), 5)
        assert_wire_equal(good.wait_for("CTToSensor")[-1].value, expected_transform(pose(5.0)))
        stats = bridge.endpoint.stats()
        assert stats["peers"] == 2 and stats["received_messages"] == 1
        polite.close()
    finally:
        good.close()


def test_a_client_that_never_reads_never_blocks_the_publisher(bridge: SlicerBridge) -> None:
    silent = socket.create_connection(("127.0.0.1", bridge.endpoint.port))
    try:
        assert bridge.endpoint.wait_for_peers(1, 10.0)
        cloud = np.random.default_rng(2).uniform(-100, 100, (5000, 3))
        done = threading.Event()

        def flood() -> None:
            for i in range(300):  # ~80 MB in all: far more than the socket buffers and the queue limit
                bridge.send_cloud(cloud + i, i + 1)
                bridge.send_pose(pose(float(i)), i + 1)
            done.set()

        threading.Thread(target=flood, daemon=True).start()
        assert done.wait(60.0), "publishing blocked on a client that does not read"
        stats = bridge.endpoint.stats()
        assert stats["dropped_messages"] > 0
        # The slow client catches up on the newest state: the last pose arrives, old ones were dropped.
        reader = Recorder(silent)
        last = reader.wait_for("CTToSensor", 1, 60.0)
        deadline = time.monotonic() + 60
        while not np.allclose(last[-1].value[0, 3], 299.0) and time.monotonic() < deadline:
            time.sleep(0.05)
            last = reader.of("CTToSensor")
        assert last[-1].value[0, 3] == pytest.approx(299.0)
        assert len(last) < 300
        reader.close()
    finally:
        silent.close()


def test_port_in_use_is_one_clear_error(bridge: SlicerBridge) -> None:
    with pytest.raises(InputError, match=f"cannot listen for OpenIGTLink on 127.0.0.1:{bridge.endpoint.port}"):
        IgtlServer("127.0.0.1", bridge.endpoint.port)


def test_client_role_waits_for_slicer_and_reconnects() -> None:
    port = free_port()
    client = IgtlClient("127.0.0.1", port, reconnect_period_s=0.1)
    bridge = SlicerBridge(SlicerConfig(role="client", host="127.0.0.1", port=port), client)
    try:
        bridge.send_pose(pose(1.0), 1)  # kept as state while Slicer is absent
        time.sleep(0.3)
        assert "refused" in client.last_error and client.peer_count() == 0
        slicer = SlicerServerStandIn(port)  # Slicer's connector (type Server) starts on the port tried
        first = slicer.wait_connected()
        assert_wire_equal(first.wait_for("CTToSensor")[0].value, expected_transform(pose(1.0)))
        slicer.close()  # ... and stops: the client reconnects once it listens again
        again = SlicerServerStandIn(port)
        bridge.send_pose(pose(2.0), 2)
        second = again.wait_connected()
        assert_wire_equal(second.wait_for("CTToSensor")[-1].value, expected_transform(pose(2.0)))
        assert client.stats()["connections"] == 2
        again.close()
    finally:
        client.close()


def test_client_mode_talks_to_pyigtls_server() -> None:
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    port = free_port()
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)  # installs its own signal handlers
    try:
        config = SlicerConfig(role="client", host="127.0.0.1", port=port)
        bridge = SlicerBridge(config, open_endpoint(config))
        assert bridge.endpoint.wait_for_peers(1, 10.0)
        bridge.send_pose(pose(6.0), 6)
        assert_wire_equal(server.wait_for_message("CTToSensor", timeout=10).matrix, expected_transform(pose(6.0)))
        bridge.endpoint.close()
    finally:
        server.stop()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)


def test_picture_is_drawn_from_what_a_peer_received(bridge: SlicerBridge, tmp_path) -> None:
    from liver_p2p_reg.igtl.picture import collect, draw
    from liver_p2p_reg.igtl.wire import StreamReader

    rng = np.random.default_rng(3)
    model, cloud = rng.uniform(-80, 80, (700, 3)), rng.uniform(-40, 40, (300, 3))
    peer = socket.create_connection(("127.0.0.1", bridge.endpoint.port))
    assert bridge.endpoint.wait_for_peers(1, 10.0)
    bridge.send_model(model, stamp_ns=1)
    bridge.send_cloud(cloud, 2)
    bridge.send_pose(pose(9.0), 2)
    bridge.send_status("WARN", "registered: residual 5.00 mm (residual above 4 mm)", 2)
    assert bridge.endpoint.flush(10.0)
    bridge.endpoint.close()  # the peer reads to the end of the stream
    reader, messages = StreamReader(), []
    while data := peer.recv(1 << 20):
        messages += reader.feed(data)
    config = bridge.config
    arrived = collect(messages, config.model_device, config.cloud_device, config.transform_device, config.status_device)
    np.testing.assert_allclose(arrived.model_ras, (model * [-1, -1, 1]).astype(np.float32))
    np.testing.assert_allclose(arrived.cloud, cloud.astype(np.float32))
    assert arrived.model_triangles == 0 and arrived.status.startswith("WARN: registered")
    assert_wire_equal(arrived.transform, expected_transform(pose(9.0)))
    assert {d: n for d, (_, n, _) in arrived.counts.items()} == {d: 1 for d in arrived.counts} and len(
        arrived.counts
    ) == 4
    png = draw(arrived, tmp_path / "what.png", title="test")
    assert png.stat().st_size > 10_000


def test_peers_beyond_the_limit_are_refused_and_a_good_one_still_served(bridge: SlicerBridge) -> None:
    from liver_p2p_reg.igtl.endpoint import MAX_PEERS

    # each idle peer may hold a message being read: without a limit, many of them grew the bridge without bound
    idle = [socket.create_connection(("127.0.0.1", bridge.endpoint.port), timeout=10) for _ in range(MAX_PEERS + 4)]
    try:
        deadline = time.monotonic() + 10
        while bridge.endpoint.stats().get("refused_connections", 0) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
        stats = bridge.endpoint.stats()
        assert stats["peers"] == MAX_PEERS and stats["refused_connections"] == 4
        assert all(hung_up(s, timeout_s=5.0) for s in idle[MAX_PEERS:])  # the last four were closed at once
    finally:
        for s in idle:
            s.close()
    deadline = time.monotonic() + 10
    while bridge.endpoint.stats()["peers"] and time.monotonic() < deadline:
        time.sleep(0.05)
    good = Recorder.connect(bridge.endpoint.port)
    try:
        bridge.send_pose(pose(5.0), 5)
        assert_wire_equal(good.wait_for("CTToSensor")[-1].value, expected_transform(pose(5.0)))
    finally:
        good.close()
