"""What the experiments share: domain config schemas, robot specs, figures, the E-KM ablation rows."""
