"""The sensor's microcontroller over a serial port: the frame codec (sans-I/O), the device clock
estimate, the live serial source, and an emulator that plays recordings through a pseudo-terminal as
the microcontroller would. See docs/serial-protocol.md.
"""
