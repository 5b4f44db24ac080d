"""DOPE stage of n2d: training, ONNX export, evaluation and the live pose estimation node."""
