"""The contracts the payload, the SITL and the ground station share, and only those.

The sample log and its header, the storage building and frames (eqs. 3-6), the servo waveform
(eqs. 1-2) and servo model, the rangefinder spec, the live-stream wire format, the signing-key
loader, the run-directory names and the command-line conventions. Everything here imports numpy
and the standard library only: the ground station imports this package and nothing else of
`firmware_py`, and the payload installs on its companion computer without the simulator.
"""
