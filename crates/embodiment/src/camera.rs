//! Pinhole cameras with OpenCV distortion.
