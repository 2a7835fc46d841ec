"""edgecal's own renderer of chessboard images with exact ground truth (tests, demo, benchmarks).

See docs/synth.md. Modules: camera (OpenCV camera model, pixel <-> ray), panels (the scene's flat panels),
render (ray-casting panels), corners (exact corner projections without an image),
photometric (light, blur, response, noise), clutter (backgrounds), truth (the "edgecal-synth-gt/1"
JSON), view (one rendered view), scenes (ready-made scene generators), writer (PNG + JSON on disk).
"""
