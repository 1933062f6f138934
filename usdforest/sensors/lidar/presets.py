"""The lidar presets: the robotics scanners (spinning, and a depth camera) and the survey
scanners of forest remote sensing (terrestrial, drone and airborne), each from its datasheet
as the comments cite it."""

from __future__ import annotations

from usdforest.sensors.lidar.patterns import (
    LineScanner,
    OscillatingScanner,
    RosetteScanner,
    TerrestrialScanner,
)
from usdforest.sensors.lidar.scanners import DepthCamera, LaserScanner, SpinningLidar

# Divergence: VLP-16 3 mrad (the sister VLS-128's manual gives 3.0 x 1.5; the VLP-16's own
# figure is unpublished), HDL-32E 3.3 mrad (its manual's 4" x 2" spot at 100 ft, the wider
# side), OS1-64 2.3 mrad (0.13 deg FWHM); Velodyne's dual mode reports strongest and last,
# the OS1 (older firmware) the strongest. See docs/notes/lidar-radiometry.md.
#
# Detection and noise (docs/guide/sensors.md has the quotes): VLP-16 no return nearer than
# 0.9 m (the ROS velodyne driver's min_range; "no points returned ... at less than about 0.9
# meters"), 100 m range (its reflectance unstated: taken at 80 %, as Ouster states its own),
# +-3 cm range accuracy read as one standard deviation (HELIOS++ models the VLP-16 so),
# rays followed to 130 m (the ROS driver's max_range; the packet's 2 mm x 65,535); HDL-32E
# "Valid Data Range 5 cm to 100 m" (its accuracy not found in its manual: the VLP-16's); OS1
# 0.8 m and "120 m @ 80%" ("40 m @ 10%" agrees within 12 %), "+-3 cm (1 sigma)" at SNR 100.
# Intensity noise: 5 % (a stated choice; no datasheet gives one). Pulse: 4 ns at half maximum,
# HELIOS++'s VLP-16 (no maker states its pulse; a stated choice for all three).
_DATASHEET = {
    "range_noise": 0.03,
    "intensity_noise": 0.05,
    "detect_reflectance": 0.8,
    "pulse_width": 4.0,
}
ROBOTICS: dict[str, SpinningLidar | DepthCamera] = {
    "vlp-16": SpinningLidar(channels=16, vfov_min=-15.0, vfov_max=15.0, azimuth_step=0.2,
                            max_range=130.0, divergence=3.0, returns="dual", min_range=0.9,
                            detect_range=100.0, model="Velodyne VLP-16", **_DATASHEET),
    "hdl-32": SpinningLidar(channels=32, vfov_min=-30.67, vfov_max=10.67, azimuth_step=0.16,
                            max_range=130.0, divergence=3.3, returns="dual", min_range=0.05,
                            detect_range=100.0, model="Velodyne HDL-32E", **_DATASHEET),
    "os1-64": SpinningLidar(channels=64, vfov_min=-16.6, vfov_max=16.6, azimuth_step=0.35,
                            max_range=150.0, divergence=2.3, min_range=0.8,
                            detect_range=120.0, model="Ouster OS1-64", **_DATASHEET),
    "depth-camera": DepthCamera(640, 480, 87.0, 10.0),
}  # fmt: skip

# Survey scanners. [H]: HELIOS++'s scanner definitions (3dgeo-heidelberg/helios,
# python/helios/data/scanners_tls.xml and scanners_als.xml), which take their figures from
# the makers' datasheets; [R]: recalled from the maker's datasheet, not confirmed from a copy
# here (docs/guide/surveys.md lists each figure and its source). Divergence as [H] gives it;
# "accuracy" as the range noise (one standard deviation), as [H] uses it; pulse width 4 ns
# (no maker states it: the robotics presets' choice).
SURVEY: dict[str, LaserScanner] = {
    # RIEGL VZ-400 [H]: 300 kHz (of 100/300), 0.3 mrad, 5 mm, 1.5 m minimum range, the head
    # at up to 60 deg/s; +60/-40 deg x 360 deg [R] (quoted in HELIOS++ issue 312); 160 m at
    # 20 % reflectance at 300 kHz [R]; near-infrared, taken as 1550 nm [R]; online waveform
    # processing: up to 5 returns (a stated choice); the step 0.1 deg (the user's to set).
    "vz-400": TerrestrialScanner(pulse_rate=300e3, vfov_min=-40.0, vfov_max=60.0,
                                 azimuth_step=0.1, elevation_step=0.1, max_range=600.0,
                                 divergence=0.3, range_noise=0.005, min_range=1.5,
                                 detect_range=160.0, detect_reflectance=0.2, returns="all",
                                 max_returns=5, return_separation=0.8, wavelength=1550.0,
                                 model="RIEGL VZ-400", intensity_noise=0.05, pulse_width=4.0),
    # RIEGL VUX-1UAV [H]: 300 kHz (of 50-550), 9 returns at 300 kHz, 330 deg field of view
    # (so 275 k pulses a second within it), 10-200 lines/s (100 here), 0.5 mrad, 10 mm, 3 m
    # minimum; 1550 nm and 350 m at 20 % [R].
    "vux-1uav": LineScanner(pulse_rate=275e3, scan_rate=100.0, fov=330.0, max_range=1000.0,
                            divergence=0.5, range_noise=0.01, min_range=3.0,
                            detect_range=350.0, detect_reflectance=0.2, returns="all",
                            max_returns=9, return_separation=1.0, wavelength=1550.0,
                            model="RIEGL VUX-1UAV", intensity_noise=0.05, pulse_width=4.0),
    # Livox Mid-40 [H]: 905 nm, 100 kHz, prisms at +121.567 and -77.733 Hz (+7294 and -4664
    # rpm: Liu, Zhang and Hong 2022, IEEE/ASME Trans. Mechatronics,
    # doi:10.1109/TMECH.2021.3058173), wedges of 18 deg at n = 1.5095: each deflects
    # (n - 1) 18 = 9.17 deg, a 36.7 deg circle (the datasheet's 38.4 deg [R]); 2 cm, 2 m
    # minimum, one return; 2.7 mrad (HELIOS++'s round beam for the 0.03 x 0.28 deg one);
    # 130 m at 20 % [R].
    "livox-mid-40": RosetteScanner(pulse_rate=100e3, fov=36.7, prism_rate_1=121.567,
                                   prism_rate_2=-77.733, max_range=260.0, divergence=2.7,
                                   range_noise=0.02, min_range=2.0, detect_range=130.0,
                                   detect_reflectance=0.2, returns="strongest",
                                   max_returns=1, model="Livox Mid-40", intensity_noise=0.05,
                                   pulse_width=4.0),
    # RIEGL VQ-780i [H]: 500 kHz (of 150-1000; 10 returns there), a rotating polygon at 20-300
    # lines/s (150 here), 60 deg (+-30), 0.25 mrad, 20 mm, 100 m minimum; 1064 nm [R].
    "vq-780i": LineScanner(pulse_rate=500e3, scan_rate=150.0, fov=60.0, max_range=6000.0,
                           divergence=0.25, range_noise=0.02, min_range=100.0,
                           returns="all", max_returns=10, return_separation=1.5,
                           wavelength=1064.0, model="RIEGL VQ-780i", intensity_noise=0.05,
                           pulse_width=4.0),
    # Leica ALS50-II [H]: 150 kHz (of 20/60/150), an oscillating mirror at up to 90 lines/s
    # (40 here), 75 deg (+-37.5), 0.22 mrad, 50 mm, 200 m minimum, 4 returns 3.5 m apart;
    # 1064 nm [R].
    "als50-ii": OscillatingScanner(pulse_rate=150e3, scan_rate=40.0, fov=75.0,
                                   max_range=6000.0, divergence=0.22, range_noise=0.05,
                                   min_range=200.0, returns="all", max_returns=4,
                                   return_separation=3.5, wavelength=1064.0,
                                   model="Leica ALS50-II", intensity_noise=0.05,
                                   pulse_width=4.0),
}  # fmt: skip
PRESETS: dict[str, LaserScanner | DepthCamera] = {**ROBOTICS, **SURVEY}
