"""The built-in backends (pytorch, torchscript, onnxruntime), registered through entry points like any plugin."""
