"""The simulated bench: CANopen devices on python-can's virtual bus, driven by the plant.

``bench.SimBench`` is the entry point; ``devices`` holds the drive and sensor
nodes, ``trajectory`` the drive's profile-velocity generator and ``eeprom`` the
drive's persistent memory.
"""
