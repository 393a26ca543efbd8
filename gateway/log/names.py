"""The names a session log is read by: topics, metadata records, attachments, schema names.

A reader finds everything of a session by these names (``docs/recording.md`` lists the layout);
the Foxglove topics are in :mod:`gateway.log.foxglove`, the zenoh key of each sample in
:mod:`gateway.keys`.
"""
from __future__ import annotations

MAGIC = b"\x89MCAP0\r\n"                   # every MCAP file starts (and ends) with it
CAN_TOPIC_PREFIX = "/can/"
CAN_SCHEMA_NAME = "bsc.CanFrame"
RECORDING_METADATA = "bsc.recording"      # written by the recorder into every file
SESSION_METADATA = "bsc.session"          # add_session_context(): software version, scenario name
ZENOH_KEYS_METADATA = "zenoh.keys"        # add_session_context(zenoh_keys=...): name -> key expr
URDF_ATTACHMENT = "robot.urdf"
SCENARIO_ATTACHMENT = "scenario.toml"
DBC_ATTACHMENT_PREFIX = "dbc/"            # one attachment per DBC file: dbc/<file name>
JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"   # declared by every channel's schema
