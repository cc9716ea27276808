"""Maps the top-level folders protocol/, server/ and client/ into the one ``facecast`` namespace."""

from setuptools import find_packages, setup

ROOTS = {"protocol": "facecast.protocol", "server": "facecast.server", "client": "facecast.client"}

packages, package_dir = [], {}
for folder, name in ROOTS.items():
    package_dir[name] = folder
    packages.append(name)
    for sub in find_packages(folder):
        packages.append(f"{name}.{sub}")
        package_dir[f"{name}.{sub}"] = f"{folder}/{sub.replace('.', '/')}"

setup(
    packages=packages,
    package_dir=package_dir,
    package_data={
        "": ["*.json", "*.npz", "*.cl", "*.txt", "*.md", "py.typed", "data/*.json", "data/*.npz"],
        "facecast.client": ["web/*.html", "web/*.css", "web/js/*.js"],
    },
    include_package_data=True,
)
