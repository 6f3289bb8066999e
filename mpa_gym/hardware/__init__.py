"""Hardware rig: wire protocol, transports, device emulator and the hardware env."""
