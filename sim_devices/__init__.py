"""Simulated twins of the rig's devices, speaking the real byte protocols.

Importing this package registers the pyserial URL handlers (``sim-shot702://``,
``sim-fw102c://``) so that ``serial.serial_for_url`` can open them; drivers need
no change to talk to a twin.
"""

import serial

_HANDLERS = "sim_devices.serial_handlers"
if _HANDLERS not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(_HANDLERS)
