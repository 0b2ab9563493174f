"""Controller manager, controllers and the hardware-component interface they meet at."""
