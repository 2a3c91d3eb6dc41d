"""Model names to classes (entry points and augmented specs), and fitted models on disk."""
