"""SDFormat models, loadable as package://maglev_haptics/<file>."""

from pathlib import Path

PACKAGE_XML = Path(__file__).with_name("package.xml")
