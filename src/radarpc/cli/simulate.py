"""``radarpc simulate {radial,coloradar}``: write a simulated dataset in the real on-disk layout."""
from __future__ import annotations


def add_parser(sub) -> None:
    from radarpc.cli import simulate_coloradar, simulate_radial

    p = sub.add_parser("simulate", help="write a simulated dataset (RADIal or ColoRadar layout)")
    kinds = p.add_subparsers(dest="kind", required=True, metavar="KIND")
    simulate_radial.add_parser(kinds)
    simulate_coloradar.add_parser(kinds)
