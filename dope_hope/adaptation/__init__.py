"""`dope-hope adapt`: a model taught its lab's domain by its own labels of unlabelled RGB-D
frames, with the depth as the teacher (settings, evidence, frames, labelling, label_set,
finetune, run)."""
