"""What runs a simulated survey: lockstep in one process (`fly`), or networked in real time (`serve`)."""
