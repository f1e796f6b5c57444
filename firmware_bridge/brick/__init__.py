"""The brick program: protocol codec, fixed-rate control loop and hardware layer (MicroPython-safe)."""
