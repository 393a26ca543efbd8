"""Child process of the SIGKILL test: records raw CAN frames at a steady rate until killed.

Prints ``flushed <n> received <n>`` lines (stats.flushed: messages in chunks the recorder has
handed to the OS, which a SIGKILL cannot take back). Frame ``i`` carries ``i`` in its payload.
Usage: python -m tests.gateway.log._crash_child OUT.mcap RATE_HZ
"""
from __future__ import annotations

import sys
import time

import can

from gateway.log.recorder import Recorder


def main() -> None:
    path, rate = sys.argv[1], float(sys.argv[2])
    batch = 20
    period = batch / rate
    rec = Recorder(path, chunk_size=16 * 1024, flush_interval_s=0.2)
    rec.add_session_context(urdf_text="<robot name='crash'/>", software="crash child")
    print("started", flush=True)
    i = 0
    next_t = time.monotonic()
    while True:
        for _ in range(batch):
            msg = can.Message(timestamp=1.0 + i / rate, arbitration_id=0x200 + i % 4,
                              data=i.to_bytes(8, "little"), channel="vcan0")
            if not rec.record_can("ft0", msg):
                print("refused", i, flush=True)
            i += 1
        s = rec.stats
        print(f"flushed {s.flushed} received {s.received}", flush=True)
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))


if __name__ == "__main__":
    main()
