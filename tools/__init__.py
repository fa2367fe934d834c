"""Developer tools: the vcan runner, the fake systemd notify socket, simulator launchers."""
