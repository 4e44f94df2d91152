"""The world the LiDAR sees: the storage building and its stockpile, ray traced."""
