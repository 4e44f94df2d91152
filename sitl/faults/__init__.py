"""Fault injection: the schedule of link, device and power faults, and its live MAVLink parameters."""
