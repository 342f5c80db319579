"""minretarget: correspondence-free online dense human motion retargeting on the CPU."""
