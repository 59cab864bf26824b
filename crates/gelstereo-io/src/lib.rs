//! Frame sources (image folders, stereo recordings, video files, cameras) and exports (CSV, JSON, PLY).
