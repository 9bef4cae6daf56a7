"""Loopback TCP server base for the emulator's wire servers (SCPI supply, fault control, socketcand).

One listening socket on host:port (port 0: a free one), one selector thread serving every client.
Subclasses override the hooks they need:

    on_accept(sock, addr)   per-client state for a new connection (default: a line buffer)
    on_readable(sock)       the client has data (default: `recv`, then newline framing)
    handle_line(sock, line) one received line, without its b"\\n" (for the default framing)
    line_too_long(sock)     the unterminated rest exceeds `max_line_bytes` (it is discarded)
    after_events()          after each select round (timeout 0.1 s)
    on_drop(sock, state)    a client is being dropped (before its socket is closed)

A hook that raises drops that client (logged), never the server.
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading

log = logging.getLogger(__name__)

CLIENT_TIMEOUT_S = 2.0  # blocking sends to a client that stops reading give up after this
SELECT_TIMEOUT_S = 0.1
RECV_BYTES = 4096


class TcpServer:
    """Listening socket + selector thread; `_clients` maps each client socket to its state."""

    max_line_bytes = 4096
    log = log  # subclasses log to their own module's logger

    def __init__(self, name: str, host: str = "127.0.0.1", port: int = 0, backlog: int = 4):
        self.name = name
        self._listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listen.bind((host, port))
        self._listen.listen(backlog)
        self._listen.setblocking(False)
        self.host, self.port = self._listen.getsockname()[:2]
        self._clients: dict[socket.socket, object] = {}
        self._clients_lock = threading.Lock()
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listen, selectors.EVENT_READ)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._serve, name=name, daemon=True)]

    # -- lifecycle ---------------------------------------------------------------------------------
    def start(self):
        for t in self._threads:
            t.start()
        return self

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)
        with self._clients_lock:
            clients = list(self._clients)
            self._clients.clear()
        for sock in clients:
            close_quietly(sock)
        close_quietly(self._listen)
        self._sel.close()

    # -- selector thread ---------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                events = self._sel.select(timeout=SELECT_TIMEOUT_S)
            except OSError:
                break
            for key, _ in events:
                if key.fileobj is self._listen:
                    self._accept()
                else:
                    self._guarded(key.fileobj, self.on_readable)
            self.after_events()

    def _accept(self) -> None:
        try:
            sock, addr = self._listen.accept()
        except OSError:
            return
        sock.settimeout(CLIENT_TIMEOUT_S)
        self._guarded(sock, self._register, addr)

    def _register(self, sock: socket.socket, addr) -> None:
        state = self.on_accept(sock, addr)
        with self._clients_lock:
            self._clients[sock] = state
        self._sel.register(sock, selectors.EVENT_READ)

    def _guarded(self, sock: socket.socket, hook, *args) -> None:
        try:
            hook(sock, *args)
        except Exception:  # never let one client take the server down
            self.log.exception("%s: error while serving a client", self.name)
            self.drop(sock)

    # -- hooks -------------------------------------------------------------------------------------
    def on_accept(self, sock: socket.socket, addr) -> object:
        return bytearray()

    def on_readable(self, sock: socket.socket) -> None:
        data = self.recv(sock)
        if data:
            self._split_lines(sock, data)

    def handle_line(self, sock: socket.socket, line: bytes) -> None:
        raise NotImplementedError

    def line_too_long(self, sock: socket.socket) -> None:
        self.log.warning("%s: over-long line dropped", self.name)

    def after_events(self) -> None:
        pass

    def on_drop(self, sock: socket.socket, state) -> None:
        pass

    def client_closed(self, sock: socket.socket) -> None:
        """The client hung up (or its socket failed)."""
        self.drop(sock)

    # -- helpers -----------------------------------------------------------------------------------
    def recv(self, sock: socket.socket) -> bytes | None:
        """Received bytes; None if there is nothing to read after all, or the client hung up (then it
        has been dropped)."""
        try:
            data = sock.recv(RECV_BYTES)
        except (socket.timeout, BlockingIOError):
            return None
        except OSError:
            data = b""
        if not data:
            self.client_closed(sock)
            return None
        return data

    def _split_lines(self, sock: socket.socket, data: bytes) -> None:
        buf = self._clients.get(sock)
        if buf is None:
            return
        buf += data
        while self._clients.get(sock) is buf:  # stop once a reply failed and dropped the client
            nl = buf.find(b"\n")
            if nl < 0:
                if len(buf) > self.max_line_bytes:
                    buf.clear()
                    self.line_too_long(sock)
                break
            line = bytes(buf[:nl])
            del buf[: nl + 1]
            self.handle_line(sock, line)

    def send(self, sock: socket.socket, text: str) -> bool:
        """Send text (ASCII) to a client; a client that cannot take it is dropped (False)."""
        try:
            sock.sendall(text.encode("ascii"))
        except OSError as exc:
            self.log.info("%s: send failed (%s), dropping the client", self.name, exc)
            self.drop(sock)
            return False
        return True

    def drop(self, sock: socket.socket) -> None:
        with self._clients_lock:
            state = self._clients.pop(sock, None)
        self.on_drop(sock, state)
        try:
            self._sel.unregister(sock)
        except (KeyError, ValueError, OSError):
            pass
        close_quietly(sock)


def close_quietly(sock) -> None:
    try:
        sock.close()
    except OSError:
        pass
