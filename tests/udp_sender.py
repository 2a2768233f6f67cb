"""Send a telemetry log's MAVLink frames over UDP to 127.0.0.1:PORT, paced by the log's
stamps, as a vehicle's link would (standard library only, so a test can run it as a
process of its own):

    python tests/udp_sender.py LOG.tlog PORT [SPEED]

It first waits until something has bound the port (the listener is ready), then sends each
frame at SPEED x real time (default 1) and prints the number of frames sent. Exit 1 when
nothing bound the port within ``READY_S``.
"""
from __future__ import annotations

import socket
import struct
import sys
import time
from pathlib import Path

READY_S = 60.0        # s: the longest wait for the listener


def tlog_frames(path: Path) -> list[tuple[int, bytes]]:
    """(unix microseconds, MAVLink frame bytes) of each message of a tlog."""
    data, out, i = Path(path).read_bytes(), [], 0
    while i + 10 <= len(data):
        usec = struct.unpack(">Q", data[i:i + 8])[0]
        magic, n_payload = data[i + 8], data[i + 9]
        n = n_payload + (8 if magic == 0xFE else 12 + (13 if data[i + 10] & 1 else 0))
        out.append((usec, data[i + 8:i + 8 + n]))
        i += 8 + n
    return out


def wait_bound(port: int, timeout: float = READY_S) -> bool:
    """True once a socket of another process (or thread) holds UDP 127.0.0.1:``port``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                probe.bind(("127.0.0.1", port))
        except OSError:
            return True
        time.sleep(0.05)
    return False


def send_frames(frames: list[tuple[int, bytes]], port: int, speed: float = 1.0) -> int:
    """Send each frame to 127.0.0.1:``port`` when its stamp is due at ``speed`` x real
    time; the number sent."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        t0, u0 = time.perf_counter(), frames[0][0]
        for usec, frame in frames:
            wait = t0 + (usec - u0) * 1e-6 / speed - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            s.sendto(frame, ("127.0.0.1", port))
    return len(frames)


def main(argv: list[str]) -> int:
    path, port = Path(argv[0]), int(argv[1])
    speed = float(argv[2]) if len(argv) > 2 else 1.0
    frames = tlog_frames(path)
    if not wait_bound(port):
        print(f"nothing listens on UDP 127.0.0.1:{port}", file=sys.stderr)
        return 1
    print(send_frames(frames, port, speed), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
