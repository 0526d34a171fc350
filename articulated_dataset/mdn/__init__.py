"""articulated_dataset.mdn"""
