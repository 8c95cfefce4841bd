"""Training: dataset and augmentation, targets' labels, loss, schedule, validation, the loop."""
