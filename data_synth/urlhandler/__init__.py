"""pyserial URL handlers of psmini (``serial.protocol_handler_packages``): ``psminisim://`` for the simulator."""
