"""articulated_dataset.baselines"""
