"""Models: encoders (DenseNet-121, EfficientNet-Lite), the D3-Net decoder and heads, MC dropout, calibration."""
