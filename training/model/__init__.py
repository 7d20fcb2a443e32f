"""neumip.training.model: the NeuMIP material as torch modules (pyramid, neural offset, relief,
classical base, map encoder). Pure torch: no files, no progress bars."""
