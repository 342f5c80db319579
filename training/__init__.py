"""training: the PyTorch reference for minretarget: data, models, losses, training, export."""
