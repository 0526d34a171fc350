"""articulated_dataset.loaders"""
