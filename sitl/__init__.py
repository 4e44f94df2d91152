"""Software-in-the-loop: storage world, stockpiles, missions and vehicle plants."""
