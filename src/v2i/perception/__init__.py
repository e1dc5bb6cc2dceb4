"""Camera perception: the ONNX image detector (``detector``), calibration and ground mapping."""
