"""The paper's evaluation: real datasets with ground truth and the synthetic experiment."""
