"""Drivers: one folder per device, each a sans-I/O protocol core, an asyncio client and a twin."""
