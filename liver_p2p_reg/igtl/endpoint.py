"""Non-blocking OpenIGTLink endpoints: a server Slicer connects to, and a client that connects to Slicer.

One daemon thread owns the sockets. `publish` (from any thread) only queues bytes and wakes it,
so a slow, absent or misbehaving peer never blocks the caller. Each peer has its own bounded
queue: a newer state of a device (a transform, a model) replaces an older one not yet sent, and
the oldest messages are dropped beyond the limits. A peer that sends garbage is disconnected; a peer that connects
(or reconnects) first gets the latest message of every device.
"""

from __future__ import annotations

import errno
import logging
import os
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable

from liver_p2p_reg.errors import InputError
from liver_p2p_reg.igtl.wire import ProtocolError, StreamReader

LogFn = Callable[[int, str], None]
_LOG = logging.getLogger("liver_p2p_reg.igtl")
RECV_BYTES = 65536


MAX_PEERS = 16  # a server's peers at most: Slicer connects once; each peer may hold a message being read
ACCEPT_RETRY_S = 1.0  # after accept() failed (out of file descriptors), the pause before listening again


class _Peer:
    """One connected socket, its outgoing queue and its incoming stream."""

    def __init__(self, sock: socket.socket, name: str, state: list[tuple[str, bytes]]) -> None:
        self.sock = sock
        self.name = name
        self.queue: deque[tuple[str, bytes]] = deque(state)
        self.queued_bytes = sum(len(data) for _, data in state)
        self.current: memoryview | None = None  # the message being sent: never dropped half-way
        self.reader = StreamReader()

    @property
    def pending(self) -> bool:
        return bool(self.queue) or self.current is not None


class Endpoint:
    """What server and client share: the state per device, the peers, the I/O thread."""

    def __init__(self, *, max_queue_messages: int = 16, max_queue_bytes: int = 64 << 20, log: LogFn | None = None):
        self.max_queue_messages = max_queue_messages
        self.max_queue_bytes = max_queue_bytes
        self._log = log or (lambda level, text: _LOG.log(level, text))
        self._lock = threading.Lock()
        self._state: dict[str, bytes] = {}  # device key -> its latest message, for peers that connect later
        self._peers: list[_Peer] = []
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.counters = {
            "connections": 0,
            "disconnections": 0,
            "garbage_disconnections": 0,
            "dropped_messages": 0,
            "sent_messages": 0,
            "received_messages": 0,
        }

    # ---------------------------------------------------------------- any thread
    def publish(self, key: str, data: bytes, replace: bool = True) -> None:
        """Queue a message for every peer (and the latest per key for peers to come); returns at once.

        replace: a newer message replaces an older one of the same key not yet sent (a state, like a
        transform); False keeps every one (events, like each registration's verdict) within the limits.
        """
        with self._lock:
            self._state[key] = data
            for peer in self._peers:
                self._enqueue(peer, key, data, replace)
        self._wake()

    def peer_count(self) -> int:
        with self._lock:
            return len(self._peers)

    def wait_for_peers(self, count: int = 1, timeout_s: float = 10.0) -> bool:
        end = time.monotonic() + timeout_s
        while self.peer_count() < count:
            if time.monotonic() > end or self._stop.is_set():
                return False
            time.sleep(0.01)
        return True

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every peer's queue has been handed to the kernel; False on timeout."""
        end = time.monotonic() + timeout_s
        while True:
            with self._lock:
                if not any(peer.pending for peer in self._peers):
                    return True
            if time.monotonic() > end:
                return False
            time.sleep(0.005)

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {**self.counters, "peers": len(self._peers)}

    def close(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(5.0)

    # ---------------------------------------------------------------- queueing (lock held)
    def _enqueue(self, peer: _Peer, key: str, data: bytes, replace: bool) -> None:
        if replace and any(k == key for k, _ in peer.queue):  # the newer state replaces the unsent older one
            kept = [(k, d) for k, d in peer.queue if k != key]
            self.counters["dropped_messages"] += len(peer.queue) - len(kept)
            peer.queue = deque(kept)
            peer.queued_bytes = sum(len(d) for _, d in kept)
        peer.queue.append((key, data))
        peer.queued_bytes += len(data)
        while len(peer.queue) > 1 and (
            len(peer.queue) > self.max_queue_messages or peer.queued_bytes > self.max_queue_bytes
        ):
            _, old = peer.queue.popleft()
            peer.queued_bytes -= len(old)
            self.counters["dropped_messages"] += 1

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except OSError:  # buffer full (a wake-up is already pending) or closed
            pass

    # ---------------------------------------------------------------- the I/O thread
    def _start(self, name: str) -> None:
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._before_select()
                for key, mask in self._selector.select(self._select_timeout()):
                    self._handle(key.data, mask)
                for peer in list(self._peers):
                    self._write(peer)
        except Exception as exc:  # the thread must never take the process down; publishing stays harmless
            self._log(logging.ERROR, f"OpenIGTLink I/O stopped: {type(exc).__name__}: {exc}")
        finally:
            for peer in list(self._peers):
                self._close_peer(peer)
            self._close_own_sockets()
            self._selector.close()
            self._wake_r.close()
            self._wake_w.close()

    def _handle(self, tag: object, mask: int) -> None:
        if tag == "wake":
            try:
                while self._wake_r.recv(4096):
                    pass
            except BlockingIOError:
                pass
        elif isinstance(tag, _Peer):
            if mask & selectors.EVENT_READ:
                self._read(tag)
        else:
            self._handle_own(tag)

    def _read(self, peer: _Peer) -> None:
        try:
            data = peer.sock.recv(RECV_BYTES)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(peer, f"connection lost ({exc.strerror or exc})")
            return
        if not data:
            self._drop(peer, "closed the connection")
            return
        try:
            messages = peer.reader.feed(data)
        except ProtocolError as exc:
            self.counters["garbage_disconnections"] += 1
            self._drop(peer, f"sent bytes that are not OpenIGTLink ({exc}); disconnected it", logging.WARNING)
            return
        self.counters["received_messages"] += len(messages)  # what Slicer sends us is read and ignored

    def _write(self, peer: _Peer) -> None:
        if peer not in self._peers:
            return
        while True:
            if peer.current is None:
                with self._lock:
                    if not peer.queue:
                        break
                    _, data = peer.queue.popleft()
                    peer.queued_bytes -= len(data)
                peer.current = memoryview(data)
            try:
                sent = peer.sock.send(peer.current)
            except BlockingIOError:
                break
            except OSError as exc:
                self._drop(peer, f"connection lost ({exc.strerror or exc})")
                return
            peer.current = peer.current[sent:]
            if not peer.current:
                peer.current = None
                self.counters["sent_messages"] += 1
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if peer.pending else 0)
        if self._selector.get_key(peer.sock).events != events:
            self._selector.modify(peer.sock, events, peer)

    def _add_peer(self, sock: socket.socket, name: str) -> None:
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # a 106-byte TRANSFORM must not wait for Nagle
        with self._lock:
            peer = _Peer(sock, name, list(self._state.items()))
            self._peers.append(peer)
            self.counters["connections"] += 1
            count = len(self._peers)
        self._selector.register(sock, selectors.EVENT_READ, peer)
        self._log(logging.INFO, f"OpenIGTLink peer {name} connected ({count} connected)")

    def _drop(self, peer: _Peer, reason: str, level: int = logging.INFO) -> None:
        self._close_peer(peer)
        self.counters["disconnections"] += 1
        self._log(level, f"OpenIGTLink peer {peer.name} {reason}")
        self._after_drop()

    def _close_peer(self, peer: _Peer) -> None:
        with self._lock:
            if peer in self._peers:
                self._peers.remove(peer)
        try:
            self._selector.unregister(peer.sock)
        except (KeyError, ValueError):
            pass
        try:
            peer.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        peer.sock.close()

    # ---------------------------------------------------------------- what server and client add
    def _before_select(self) -> None:
        pass

    def _select_timeout(self) -> float | None:
        return None

    def _handle_own(self, tag: object) -> None:
        pass

    def _after_drop(self) -> None:
        pass

    def _close_own_sockets(self) -> None:
        pass


def _address(host: str, port: int, passive: bool) -> tuple:
    try:
        flags = socket.AI_PASSIVE if passive else 0
        return socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=flags)[0]
    except socket.gaierror as exc:
        raise InputError(f"cannot resolve OpenIGTLink host {host!r}: {exc.strerror}") from None


class IgtlServer(Endpoint):
    """Listens on host:port; every client (Slicer's connector of type Client) gets the stream."""

    def __init__(self, host: str, port: int, **kwargs) -> None:
        super().__init__(**kwargs)
        family, kind, proto, _, address = _address(host, port, passive=True)
        self._listener = socket.socket(family, kind, proto)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind(address)
            self._listener.listen(64)  # 8 dropped connects in a burst: each client then waited a second to retry
        except OSError as exc:
            self._listener.close()
            raise InputError(
                f"cannot listen for OpenIGTLink on {host}:{port}: {exc.strerror or exc} "
                "(another bridge or a Slicer server on that port?)"
            ) from None
        self._listener.setblocking(False)
        self._resume_accept_s: float | None = None  # while accept() fails: when to listen again
        self._selector.register(self._listener, selectors.EVENT_READ, "listen")
        self.host = host
        self.port = self._listener.getsockname()[1]
        self._start(f"igtl-server-{self.port}")

    def _handle_own(self, tag: object) -> None:
        while True:
            try:
                sock, address = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of file descriptors: pause, or the still-readable listener spins a core
                self._log(logging.WARNING, f"OpenIGTLink accept failed: {exc.strerror or exc}; retrying in 1 s")
                self._selector.unregister(self._listener)
                self._resume_accept_s = time.monotonic() + ACCEPT_RETRY_S
                return
            if len(self._peers) >= MAX_PEERS:  # counted in the stats, not logged per try (a flood would flood it)
                sock.close()
                self.counters["refused_connections"] = self.counters.get("refused_connections", 0) + 1
                continue
            self._add_peer(sock, f"{address[0]}:{address[1]}")

    def _before_select(self) -> None:
        if self._resume_accept_s is not None and time.monotonic() >= self._resume_accept_s:
            self._resume_accept_s = None
            self._selector.register(self._listener, selectors.EVENT_READ, "listen")

    def _select_timeout(self) -> float | None:
        return None if self._resume_accept_s is None else max(0.0, self._resume_accept_s - time.monotonic())

    def _close_own_sockets(self) -> None:
        self._listener.close()


class IgtlClient(Endpoint):
    """Connects to host:port (Slicer's connector of type Server) and reconnects whenever it is lost."""

    def __init__(self, host: str, port: int, reconnect_period_s: float = 1.0, **kwargs) -> None:
        super().__init__(**kwargs)
        self.host, self.port = host, port
        self.reconnect_period_s = reconnect_period_s
        self._connecting: socket.socket | None = None
        self._next_attempt_s = 0.0
        self._failing = False  # log the first failure of a streak only
        self.last_error = ""  # why the last connection attempt failed ("" after a success)
        self._start(f"igtl-client-{port}")

    def _before_select(self) -> None:
        if self._peers or self._connecting is not None or time.monotonic() < self._next_attempt_s:
            return
        try:
            family, kind, proto, _, address = _address(self.host, self.port, passive=False)
        except InputError as exc:
            self._failed(str(exc))
            return
        sock = socket.socket(family, kind, proto)
        sock.setblocking(False)
        code = sock.connect_ex(address)
        if code not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            sock.close()
            self._failed(os.strerror(code))
            return
        self._connecting = sock
        self._selector.register(sock, selectors.EVENT_WRITE, "connecting")

    def _select_timeout(self) -> float | None:
        if self._peers or self._connecting is not None:
            return None
        return max(0.0, self._next_attempt_s - time.monotonic())

    def _handle_own(self, tag: object) -> None:
        sock, self._connecting = self._connecting, None
        if sock is None:
            return
        self._selector.unregister(sock)
        code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if code:
            sock.close()
            self._failed(os.strerror(code))
            return
        self._failing = False
        self.last_error = ""
        self._add_peer(sock, f"{self.host}:{self.port}")

    def _failed(self, reason: str) -> None:
        self.last_error = reason
        if not self._failing:
            self._log(
                logging.WARNING,
                f"cannot connect to OpenIGTLink server {self.host}:{self.port} ({reason}); "
                f"retrying every {self.reconnect_period_s:g} s",
            )
        self._failing = True
        self._next_attempt_s = time.monotonic() + self.reconnect_period_s

    def _after_drop(self) -> None:
        self._next_attempt_s = time.monotonic() + self.reconnect_period_s

    def _close_own_sockets(self) -> None:
        if self._connecting is not None:
            self._connecting.close()
