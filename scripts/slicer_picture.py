"""Draw what 3D Slicer receives from the bridge (README "See it in 3D Slicer"): a bag replayed, received over loopback."""

from __future__ import annotations

import argparse
import socket
import threading
from pathlib import Path

from liver_p2p_reg.bags.replay import replay_bags
from liver_p2p_reg.cli.slicer import finish_replay
from liver_p2p_reg.config import Config
from liver_p2p_reg.igtl.bridge import SlicerBridge, open_endpoint
from liver_p2p_reg.igtl.link import SlicerLink
from liver_p2p_reg.igtl.picture import collect, draw
from liver_p2p_reg.igtl.wire import Message, StreamReader
from liver_p2p_reg.slicer_config import SlicerConfig


def receive(port: int, into: list[Message]) -> threading.Thread:
    """A peer standing in for Slicer: connects and keeps every message until the server closes."""
    sock = socket.create_connection(("127.0.0.1", port))

    def read() -> None:
        reader = StreamReader(max_body_bytes=1 << 30)
        while data := sock.recv(1 << 20):
            into.extend(reader.feed(data))
        sock.close()

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--bag", default="bags/phantom_sim_04_vis0.36")
    parser.add_argument("--out", default="docs/slicer/what_arrives.png")
    parser.add_argument("--method", help="registration method (default: the configured one)")
    parser.add_argument("--max-frames", type=int, default=0, help="register at most this many frames (0: all)")
    args = parser.parse_args()
    slicer = SlicerConfig(host="127.0.0.1", port=0)
    endpoint = open_endpoint(slicer)
    link = SlicerLink(SlicerBridge(slicer, endpoint))
    messages: list[Message] = []
    reader = receive(endpoint.port, messages)
    assert endpoint.wait_for_peers(1, 10.0), "the stand-in peer did not connect"
    config = Config(method=args.method) if args.method else Config()
    rows = replay_bags([args.bag], config, max_frames=args.max_frames, observer=link)
    finish_replay(link, 30.0)
    reader.join(30.0)
    arrived = collect(messages, slicer.model_device, slicer.cloud_device, slicer.transform_device, slicer.status_device)
    title = f"{Path(args.bag).name}: what 3D Slicer receives ({rows[0].registered} registrations, the last shown)"
    print(draw(arrived, args.out, title))
    print(
        f"{arrived.status}\n{len(messages)} messages: "
        + ", ".join(f"{d} x{n}" for d, (_, n, _) in arrived.counts.items())
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
