"""The session log: one place for the MCAP format bsc writes and reads.

- :mod:`.names`: topics, metadata records, attachments, schema names;
- :mod:`.schema`: the JSON form of a record and its JSON schema (the zenoh payloads use the same);
- :mod:`.canframe`: the one CAN-frame codec (``bsc.CanFrame`` on ``/can/<bus>``);
- :mod:`.writer`: the MCAP writer (mcap's public records, chunks ended by the caller);
- :mod:`.recorder`: :class:`~gateway.log.recorder.Recorder`, a session to one file or a split series;
- :mod:`.foxglove`: Foxglove's well-known schemas (alerts as ``foxglove.Log``, the frame tree on ``/tf``);
- :mod:`.context`: what a log says about itself (the robot, DBCs, key scheme, ``bsc.session``):
  written (:func:`~gateway.log.context.session_context`) and read back (``read_context``);
- :mod:`.reader`: the one reader, in file or log-time order, and the raw CAN frames on it;
  :mod:`.frames` its compiled path for the frames of a whole log as rows (what a replay feeds);
- :mod:`.scan`: the record-level walk: ``bsc info`` (inspect) and ``bsc recover``;
- :mod:`.errors`: :class:`~gateway.log.errors.LogError`, :class:`~gateway.log.errors.McapFileError`;
- :mod:`.canlog`: CAN logs of other tools (candump, Vector, PEAK, python-can CSV) in and out.

The format is documented in ``docs/recording.md``; replaying a log is :mod:`gateway.replay`'s.
"""
