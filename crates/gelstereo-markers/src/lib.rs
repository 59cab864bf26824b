//! Marker localizers behind one trait: Marknet + MRE through ONNX Runtime (the paper's method), and
//! OpenCV's SimpleBlobDetector (the paper's baseline); plus the paper's detection metrics.
