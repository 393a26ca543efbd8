"""CAN frames -> validated, typed sensor samples. Knows python-can and bytes; never zenoh or Pinocchio."""
