//! 3DGS PLY.
