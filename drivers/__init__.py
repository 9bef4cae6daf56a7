"""The service's side of each wire: CANopen drive and load machine, DAQ stream, DC supply.

Every driver is chosen and configured by settings strings (python-can interface name, pyserial URL);
none of them knows whether the bench behind the wire is real or emulated.
"""

from pathlib import Path

EDS_DIR = Path(__file__).resolve().parent / "eds"
DRIVE_EDS = EDS_DIR / "drive.eds"
LOAD_EDS = EDS_DIR / "load.eds"
