"""Training for nak: the paper's Base, +Res and +Reg networks on nak's datasets, exported under nak's
ONNX model contract (docs/design.md §7) and scored through nak itself."""
