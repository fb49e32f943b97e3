"""Multi-LiDAR extrinsic calibration (`pa calibrate`), one module per job:

- `extrinsics`: the extrinsics YAML (T_base_lidar per LiDAR; xyz + roll/pitch/yaw in degrees);
- `rig_scans`: a rig folder (lidar0/, lidar1/, ...) and the matching of scans to the base's;
- `coarse`: point-to-plane ICP of each LiDAR against lidar0's map (from hand-measured extrinsics);
- `composite`: the plane cost at composite poses T_world_base T_base_lidar, exact derivatives;
- `solver`: damped Newton on base poses and extrinsics (held directions allowed);
- `observability`: the extrinsics' information with the poses marginalised, unobservable
  directions in words, the extrinsic covariance;
- `outputs`: output paths and the merged map with a LiDAR index per point;
- `run`: `CalibrationRun`, the steps of `pa calibrate`.
"""

from pa_cli.calibration.run import CalibrationRun
from pa_cli.io.extrinsics import read_extrinsics, write_extrinsics

__all__ = ["CalibrationRun", "read_extrinsics", "write_extrinsics"]
