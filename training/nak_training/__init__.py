"""Training for nak: the paper's Base, +Res and +Reg networks on nak's datasets, exported under nak's
ONNX model contract (DESIGN.md §7) and scored through nak itself."""
