"""Device drivers, written against the HAL protocols: the LIDAR-Lite v3 and the sweep servo."""
