//! The robot side of EMR-FLOAM: scan sources (simulator and recordings), odometry, keyframes.
