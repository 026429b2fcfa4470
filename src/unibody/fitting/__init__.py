"""Solvers on the body's public interface: pose inversion, the articulated Gauss-Newton, identity fitting."""
