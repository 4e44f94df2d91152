"""The simulated quadcopter: JSBSim's F450 plant flown by our autopilot, an ideal plant, a kinematic
stand-in, and the vehicle interface the MAVLink server drives."""
