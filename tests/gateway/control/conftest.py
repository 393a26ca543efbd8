"""Two zenoh sessions on an explicit loopback endpoint (multicast scouting off), for the
compensator's service tests: one on the robot's side, one for bsc control."""
from __future__ import annotations

import pytest
import zenoh

from gateway.zenoh_config import make_config
from support import free_port


@pytest.fixture
def sessions():
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(make_config(listen=[ep])) as a, zenoh.open(make_config(connect=[ep])) as b:
        yield a, b
