"""The host side: records field and hardware-in-the-loop logs from a brick over any pyserial URL."""
