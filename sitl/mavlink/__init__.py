"""The SITL's MAVLink side: the autopilot peer any ground station can fly, and a scripted ground station."""
