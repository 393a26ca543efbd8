"""CAN frames -> validated, typed sensor samples. Knows python-can and bytes; never zenoh or Pinocchio."""

from . import jitcache as _jitcache

_jitcache.configure()     # before any kernel is compiled or loaded (drivers/jitcache.py says why)
