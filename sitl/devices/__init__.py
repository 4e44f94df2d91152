"""Emulated payload devices: what the payload's HAL talks to in the SITL instead of hardware."""
