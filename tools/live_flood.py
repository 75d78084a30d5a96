#!/usr/bin/env python3
"""Flood a live view with fragmented client messages, to see its memory stay bounded.

    python3 tools/live_flood.py HOST PORT [--clients 12] [--connections 50] [--fragments 64]

Each of --clients threads opens --connections WebSocket connections in turn (subprotocol
foxglove.sdk.v1) and on each sends one text message in --fragments masked fragments of
16 000 bytes (64: about 1 MB, past the server's 64 KiB bound). Read the daemon's peak
resident memory before and after from /proc/PID/status (VmHWM).
"""
import argparse
import socket
import threading

KEY = b"dGhlIHNhbXBsZSBub25jZQ=="


def handshake(host, port):
    s = socket.create_connection((host, port))
    s.sendall(
        b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: " + KEY + b"\r\nSec-WebSocket-Version: 13\r\n"
        b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    head = b""
    while b"\r\n\r\n" not in head:
        byte = s.recv(1)
        if not byte:
            break
        head += byte
    return s


def frame(fin, opcode, payload):
    """A masked client frame (RFC 6455 §5.2) with a 16-bit length."""
    mask = b"\x01\x02\x03\x04"
    head = bytes([(0x80 if fin else 0) | opcode, 0x80 | 126]) + len(payload).to_bytes(2, "big")
    return head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(payload))


def client(host, port, connections, fragments):
    piece = b" " * 16000
    for _ in range(connections):
        try:
            s = handshake(host, port)
            for i in range(fragments):
                s.sendall(frame(i == fragments - 1, 1 if i == 0 else 0, piece))
            s.close()
        except OSError:
            pass  # closed by the server (1009): what the bound does


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("host")
    p.add_argument("port", type=int)
    p.add_argument("--clients", type=int, default=12)
    p.add_argument("--connections", type=int, default=50)
    p.add_argument("--fragments", type=int, default=64)
    a = p.parse_args()
    threads = [
        threading.Thread(target=client, args=(a.host, a.port, a.connections, a.fragments))
        for _ in range(a.clients)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


if __name__ == "__main__":
    main()
