//! Grid indexing: gives each detection its (row, col) on the reference lattice; pairs left and right
//! views by index under the epipolar constraint.
