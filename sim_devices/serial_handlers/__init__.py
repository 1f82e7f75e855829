"""pyserial URL handlers: ``protocol_<scheme>`` modules looked up by ``serial_for_url``."""
