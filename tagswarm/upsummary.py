"""What ``tagswarm up`` prints when a run ends, from its run folder's ``metrics.json`` and
``run.json`` (presentation only: no processes, no network)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgspec
from rich.console import Console
from rich.table import Table

from tagswarm.evaluation.localised import LOCALISED_M
from tagswarm.evaluation.runsummary import controller_trouble

#: a robot whose fused position sigma (median over the run) passes this is named "weakly tied" in the summary:
#: every robot of the built-in scenes stays under 0.08 m; a 12 m x 9 m lab a user wrote, at 320x240 through the
#: realistic lens, had seven robots at 0.7-1.2 m, whose poses swung by metres
WEAKLY_TIED_SIGMA_M = 0.25


def print_controller_trouble(console: Console, out: Path) -> None:
    """Say which robots' own controllers failed or were slow (their agents carried on: counters only)."""
    try:
        counters = msgspec.json.decode((out / "run.json").read_bytes()).get("counters", {})
    except (OSError, msgspec.DecodeError, AttributeError):
        return
    for note in controller_trouble(counters):
        console.print(f"[yellow]{note} (docs/controllers.md)[/]", highlight=False)


# a robot first localised later than this (s of simulated time, and a fifth of the run) is named at the end
LATE_PLACEMENT_S = 10.0


def print_summary(console: Console, metrics: dict[str, Any], *, failed: bool = False) -> None:
    """The swarm's accuracy table, time localised, re-localisations, kidnaps and contacts, then what a
    user should look at: robots never or late placed, over 10 cm at some time, weakly tied, and the
    warnings a run folder's ``metrics`` carries (``failed``: the run crashed, say so first)."""
    swarm = metrics.get("swarm", {})
    if not swarm:
        return
    if failed:  # the hints below read the scene's geometry into what a crash cut short
        console.print("[red]the run failed (above): these numbers cover only what ran[/]", highlight=False)
    t = Table(title="swarm accuracy (map frame)")
    t.add_column("trajectory")
    t.add_column("ATE RMSE [m]")
    t.add_column("ATE max [m]")
    for name in ("fused", "odom"):
        ate = swarm.get(name, {}).get("ate_unaligned") or {}
        t.add_row(name, f"{ate.get('rmse', float('nan')):.3f}", f"{ate.get('max', float('nan')):.3f}")
    console.print(t)
    fused, kid, contacts = swarm.get("fused", {}), swarm.get("kidnaps") or {}, swarm.get("contacts") or {}
    tl, tlp = fused.get("time_localised"), fused.get("time_localised_placed")
    worst = kid.get("max_time_to_relocalise_s")
    once = "" if tlp is None else f" ({tlp:.1%} once placed)"
    console.print(f"time localised (< 10 cm) {'—' if tl is None else f'{tl:.1%}'}{once} · re-localisations "
                  f"{swarm.get('relocalisations', 0)} · kidnaps {kid.get('count', 0)} (recovered "
                  f"{kid.get('recovered', 0)}{'' if worst is None else f', slowest {worst:.1f} s'}) · contacts "
                  f"robot-robot {contacts.get('robot_robot', '—')}, obstacle {contacts.get('robot_obstacle', '—')}, "
                  f"wall {contacts.get('robot_wall', '—')}", highlight=False)
    firsts = {k: (r.get("fused") or {}).get("first_s") for k, r in metrics.get("robots", {}).items()}
    never = [k for k, f in firsts.items() if f is None]
    if never and not failed:
        origin = metrics.get("run", {}).get("origin_id")
        anchored = bool(metrics.get("run", {}).get("landmarks")) or str(origin) in never
        tie = ("no sighting of a landmark, or chain of sightings to a robot that saw one, placed them within the run; "
               "landmarks in more robots' view, or missions that pass them, help" if anchored else
               f"no chain of sightings joined them to the origin robot {origin} within the run; landmarks, a more "
               "central origin or missions that meet help")
        console.print(f"[yellow]never localised: robot(s) {', '.join(never)} of {len(firsts)} (the fused error above "
                      f"is of the other {len(firsts) - len(never)}); the server never placed them, or never vouched "
                      f"for their place (position sigma over claim_sigma_m; logs/server.log says which): {tie} "
                      "(README, 'Your own scene')[/]", highlight=False)
    end_s = metrics.get("run", {}).get("sim_time_s") or 0.0
    late = {k: f for k, f in firsts.items() if f is not None and f > max(LATE_PLACEMENT_S, 0.2 * end_s)}
    if late and not failed:
        console.print(f"[yellow]localised late: robot(s) {', '.join(f'{k} ({f:.1f} s)' for k, f in late.items())}: "
                      "no robot saw their tags well enough to place them before (too far for the camera, hidden or "
                      "out of view), or the server did not vouch for their place before (logs/server.log), and time "
                      "localised counts those seconds as lost; robots within each other's view and decoding range, "
                      "or missions that pass them, help; robots that start at known places (docks) can be in the map "
                      "from the start: --set server.start_prior_sigma=0.02 (README, 'Your own scene')[/]",
                      highlight=False)
    over = {k: ((r.get("fused") or {}).get("ate_unaligned") or {}) for k, r in metrics.get("robots", {}).items()}
    over = {k: a for k, a in over.items() if a.get("max") is not None and a["max"] >= LOCALISED_M}
    if over:
        named = ", ".join(f"{k} (max {100 * a['max']:.1f} cm, RMSE {100 * a.get('rmse', float('nan')):.1f} cm)"
                          for k, a in sorted(over.items(), key=lambda kv: -kv[1]["max"]))
        console.print(f"over {100 * LOCALISED_M:.0f} cm at some time: robot(s) {named}; when and how far each robot "
                      "was from its observers: plots/error_over_time.png, plots/error_vs_distance.png", highlight=False)
    sigmas = {k: (r.get("fused") or {}).get("sigma_median_m") for k, r in metrics.get("robots", {}).items()}
    weak: dict[str, float] = {k: float(v) for k, v in sigmas.items() if v is not None and v > WEAKLY_TIED_SIGMA_M}
    if weak:
        lo, hi = min(weak.values()), max(weak.values())
        span = f"{lo:.2f}" if hi - lo < 0.005 else f"{lo:.2f}-{hi:.2f}"
        console.print(f"[yellow]weakly tied: robot(s) {', '.join(weak)} (the map's position σ, median over the run: "
                      f"{span} m): few, far or one-way sightings join them to "
                      "the origin robot, so their poses swing within that σ; more robots in sight of each other, "
                      "landmarks or a finer camera help (README, 'Your own scene')[/]", highlight=False)
    for w in metrics.get("warnings", []):
        if ("heard nothing from" in w or "'s controller: " in w or "not applied by the world" in w
                or "stopped waiting for a participant" in w):
            console.print(f"[yellow]warning: {w}[/]", highlight=False)
