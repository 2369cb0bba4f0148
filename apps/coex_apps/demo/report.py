"""``report.html`` of a demo run, written for the scientist who has to trust it.

One self-contained HTML file: the outcome in plain words and tables, the received maps as
north-up figures in metres (inline SVG with the raster embedded as a PNG data URI), a gallery of
the received images, charts of the dive over time, the decisions taken and, folded away, the raw
metrics. The figures are matplotlib's (:mod:`.figures`).
"""

from __future__ import annotations

import base64
import io
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .figures import _e, _f, line_chart, map_figure, timeline_chart

__all__ = ["line_chart", "map_figure", "timeline_chart", "write_report"]

GALLERY_CAP = 60
#: who sees what, said once on the page (README.md and docs/demo.md say it in the same words)
WHO_SEES_WHAT = ("The scripted operator sees only what reached topside (the received map, the vehicle's "
                 "detections and statuses, the received images with their announced time and position, and the "
                 "camera's field of view); only the referee reads the simulation's truth (where every object is, "
                 "what it is, and which pixels of each frame show it), and it judges every confirmation by it.")


# ------------------------------------------------------------------------------ small helpers


def _num(v: Any, fmt: str = ".0f", unit: str = "") -> str:
    """A number for a table cell; an en dash when missing."""
    x = _f(v)
    return "\u2013" if x is None else f"{x:{fmt}}{unit}"


def _pos(x: Any, y: Any, fmt: str = ".1f") -> str:
    """An (x, y) position in metres, or an en dash."""
    fx, fy = _f(x), _f(y)
    return "\u2013" if fx is None or fy is None else f"({fx:{fmt}}, {fy:{fmt}})"


# ------------------------------------------------------------------------------ page sections


def _verdict(ok: Any) -> str:
    """MET / NOT MET, coloured; n/a when unknown."""
    if ok is None:
        return '<span class="na">n/a</span>'
    return '<span class="met">MET</span>' if ok else '<span class="notmet">NOT MET</span>'


def _scenario_line(sc: Any) -> str:
    """One line describing the scenario, tolerant of missing keys."""
    if not isinstance(sc, Mapping):
        return ""
    bits = []
    if sc.get("name") is not None:
        bits.append(f"scenario \u201c{sc['name']}\u201d")
    area = _f(sc.get("area"))
    if area is not None:
        bits.append(f"survey area {area:g} m \u00d7 {area:g} m")
    depth = _f(sc.get("water_depth"))
    if depth is not None:
        bits.append(f"water depth {depth:g} m")
    loss = sc.get("loss")
    if sc.get("loss_description"):
        bits.append(f"link: {sc['loss_description']}")
        if sc.get("modem_rate") is not None:
            bits.append(f"Micromodem rate {sc['modem_rate']}")
    elif isinstance(loss, Mapping):
        model = loss.get("model", "?")
        extra = ", ".join(f"{k} {v}" for k, v in loss.items() if k != "model" and not isinstance(v, Mapping | list))
        bits.append(f"link loss: {model}" + (f" ({extra})" if extra else ""))
    elif loss is not None:
        bits.append(f"link loss: {loss}")
    return " \u00b7 ".join(bits)


def _goals_table(goals: Any) -> str:
    """The goals with MET / NOT MET and the detail behind each."""
    if not isinstance(goals, Mapping) or not goals:
        return "<p><em>No goals were recorded.</em></p>"
    rows = "".join(
        f"<tr><td>{_e(name)}</td><td class='c'>{_verdict(g.get('met') if isinstance(g, Mapping) else None)}</td>"
        f"<td>{_e(g.get('detail', '') if isinstance(g, Mapping) else g)}</td></tr>"
        for name, g in goals.items())
    return f"<table><tr><th>goal</th><th>result</th><th>detail</th></tr>{rows}</table>"


def _targets_table(targets: Any) -> str:
    """One row per true target: when it became identifiable and when an image confirmed it."""
    if not isinstance(targets, Sequence) or not targets:
        return "<p><em>No targets in this scenario.</em></p>"
    rows = []
    for i, t in enumerate(targets):
        if not isinstance(t, Mapping):
            continue
        name = t.get("name", f"target {i + 1}")
        seen = t.get("identifiable_at_1m_s")
        seen_s = _num(seen) if _f(seen) is not None else '<span class="bad">never</span>'
        c = t.get("confirmation")
        if isinstance(c, Mapping):
            conf = (f"<td class='r'>{_num(c.get('image_id'))}</td><td class='r'>{_num(c.get('confirmed_at_s'))}</td>"
                    f"<td class='r'>{_num(c.get('bytes'), ',.0f')}</td><td class='r'>{_num(c.get('tdma_cycles'), '.2f')}</td>"
                    f"<td class='r'>{_num(t.get('decision_time_s')) if _f(t.get('decision_time_s')) is not None else '-'}</td>")
        else:
            conf = "<td colspan='5' class='bad c'>never confirmed</td>"
        rows.append(f"<tr><td>{_e(name)}</td><td>{_pos(t.get('x'), t.get('y'))}</td>"
                    f"<td class='r'>{seen_s}</td>{conf}</tr>")
    return ("<table><tr><th>target</th><th>position (m)</th><th>identifiable at 1 m (s)</th>"
            "<th>confirming image (id)</th><th>confirmed at (s)</th><th>bytes</th>"
            "<th>TDMA cycles after request</th><th>decision time (s)</th></tr>" + "".join(rows) + "</table>")


#: issue 56's bound on a target's map error and on the camera's pass over it (m)
NAV_BOUND_M = 2.0


def _navigation_section(nav: Any) -> str:
    """The vehicle's drift and topside's correction (issue 56): per true target, how far the
    corrected map put it and how far the camera's true track passed from it, judged against the
    truth; with the correction off, how far the camera missed."""
    if not isinstance(nav, Mapping) or not nav.get("active"):
        return ""
    on = nav.get("correction") == "on"
    how = ("on: the map, images and detections were shown corrected and the camera lines sent in the "
           "vehicle's frame" if on else
           "OFF (--no-correction): the operator saw the map as the vehicle made it and sent its camera "
           "lines in those coordinates, so the camera misses by the drift between mapping and the pass")
    est = nav.get("estimate")
    est1 = next(iter(est.values()), None) if isinstance(est, Mapping) and est else None
    est_txt = ""
    if isinstance(est1, Mapping) and est1.get("error_median_m") is not None:
        est_txt = (f" Topside's estimate against the true drift: median {_num(est1.get('error_median_m'), '.2f')} m, "
                   f"95th percentile {_num(est1.get('error_p95_m'), '.2f')} m, worst {_num(est1.get('error_max_m'), '.2f')} m.")

    def cell(v: Any) -> str:
        x = _f(v)
        if x is None:
            return "<td class='bad c'>none</td>"
        return f"<td class='r'>{x:.2f}</td>" if x <= NAV_BOUND_M else f"<td class='r bad'>{x:.2f}</td>"

    rows = "".join(
        f"<tr><td>target {i + 1}</td><td>{_pos(t.get('x'), t.get('y'))}</td>{cell(t.get('map_error_m'))}"
        f"{cell(t.get('camera_pass_m'))}</tr>"
        for i, t in enumerate(nav.get("targets") or []) if isinstance(t, Mapping))
    return (f'<h3>Navigation</h3><p class="note">The vehicle dead-reckons and drifts '
            f"({_num(nav.get('drift_at_end_m'), '.1f')} m at the dive's end); topside fuses the ship's USBL "
            f"fixes into an estimate of the drift. Correction {_e(how)}.{_e(est_txt)} Judged against the "
            f"truth; over {NAV_BOUND_M:g} m in red.</p>"
            "<table><tr><th>target</th><th>true position (m)</th><th>map error (m)</th>"
            "<th>camera pass: closest distance of the camera's true track (m)</th></tr>" + rows + "</table>")


def _vehicles_section(vehicles: Any) -> str:
    """One section per vehicle: its role, its link, what it overheard for the other vehicle, the
    survey commands that reached it and those it flew (the truth), its images and statuses."""
    if not isinstance(vehicles, Sequence) or not vehicles:
        return ""
    parts = []
    for v in vehicles:
        if not isinstance(v, Mapping):
            continue
        raw = v.get("link")
        link: Mapping[str, Any] = raw if isinstance(raw, Mapping) else {}
        loss = _f(link.get("frame_loss"))
        rows = [("packets sent", _num(link.get("packets_sent"), ",.0f")),
                ("bytes sent / capacity", f"{_num(link.get('used_bytes'), ',.0f')} / {_num(link.get('capacity_bytes'), ',.0f')}"),
                ("bytes delivered topside", _num(link.get("delivered_bytes"), ",.0f")),
                ("frame loss", "-" if loss is None else f"{loss:.0%}"),
                ("frames overheard for another node (not handled)", _num(v.get("frames_overheard_for_others"), ",.0f")),
                ("survey commands that reached it / it flew",
                 f"{_num(v.get('survey_commands_received'))} / {_num(v.get('survey_commands_flown'))}"),
                ("images taken", _num(v.get("images_captured"), ",.0f")),
                ("statuses received topside", _num(v.get("statuses_received_topside"), ",.0f"))]
        body = "".join(f"<tr><td>{_e(k)}</td><td class='r'>{_e(val)}</td></tr>" for k, val in rows)
        parts.append(f"<h3>Vehicle {_e(v.get('node'))}: {_e(v.get('role'))}</h3><table>{body}</table>")
    return '<h2 id="vehicles">Vehicles</h2>' + "".join(parts)


def _detections_table(items: Any, cost: Any, targets: Any) -> str:
    """The vehicle's detections as topside received them, judged against the truth, what they
    cost on the link, and per target the time from its first detection to its confirming image."""
    if not isinstance(items, Sequence) or not items:
        return "<p>Detections: <em>none received</em> (no detector on the vehicle, or nothing stood out).</p>"
    rows = []
    for d in items:
        if not isinstance(d, Mapping):
            continue
        truth = str(d.get("truth", "none"))
        cls = "ok" if truth.startswith("target") else ("bad" if truth == "none" else "")
        size = "" if d.get("length") is None else f"{_num(d.get('length'), '.1f')} x {_num(d.get('width'), '.1f')}"
        rows.append(f"<tr><td class='r'>{_num(d.get('id'))}</td><td>{_e(d.get('source'))}</td>"
                    f"<td>{_pos(d.get('x'), d.get('y'))}</td><td class='r'>{_num(d.get('score'), '.2f')}</td>"
                    f"<td class='r'>{_num(d.get('height'), '.1f')}</td><td class='r'>{size}</td>"
                    f"<td class='r'>{_num(d.get('orientation'))}</td><td class='r'>{_num(d.get('first_at_s'))}</td>"
                    f"<td class='{cls}'>{_e(truth)}</td></tr>")
    c = cost if isinstance(cost, Mapping) else {}
    words = (f"{_num(c.get('received'))} detections received: {_num(c.get('true'))} of a true target, "
             f"{_num(c.get('decoys'))} of a decoy, {_num(c.get('false'))} of nothing. They cost "
             f"{_num(c.get('bytes_sent'), ',.0f')} B of Detection messages sent by the vehicle "
             f"({_num(c.get('bytes_received'), ',.0f')} B received) and "
             f"{_num(c.get('neighbourhood_bytes_sent'), ',.0f')} B of 1 m subgrids sent around them.")
    per = []
    for t in targets if isinstance(targets, Sequence) else ():
        if not isinstance(t, Mapping):
            continue
        fd = t.get("first_detection")
        dc = t.get("detection_to_confirmation_s")
        per.append(f"{_e(t.get('name'))}: " + ("never detected" if not isinstance(fd, Mapping) else
                   f"first detected topside at {_num(fd.get('first_at_s'))} s"
                   + (f", confirmed {_num(dc)} s later" if _f(dc) is not None else ", not confirmed")))
    return (f'<p class="note">{words} {"; ".join(per)}.</p>'
            "<table><tr><th>id</th><th>found in</th><th>position (m)</th><th>score</th><th>height (m)</th>"
            "<th>length x width (m)</th><th>orientation (deg)</th><th>first received (s)</th>"
            "<th>what is really there</th></tr>" + "".join(rows) + "</table>")


def _false_table(items: Any) -> str:
    """Candidates confirmed by an image that showed something other than a target."""
    if not items:
        return '<p>False confirmations: <span class="ok">none</span>.</p>'
    rows = "".join(
        f"<tr><td>{_pos(f.get('x'), f.get('y'))}</td><td class='r'>{_num(f.get('image_id'))}</td>"
        f"<td class='r'>{_num(f.get('confirmed_at_s'))}</td><td>{_e(f.get('shows', '?'))}</td></tr>"
        for f in items if isinstance(f, Mapping))
    return (f'<p class="bad">False confirmations: {len(items)}</p><table class="false">'
            "<tr><th>candidate position (m)</th><th>image id</th><th>confirmed at (s)</th>"
            f"<th>what the image showed</th></tr>{rows}</table>")


def _surveys_table(items: Any) -> str:
    """Every survey command topside sent: what it asked, each state as topside heard it, and what
    the vehicle really did (the truth)."""
    if not items:
        return "<p><em>No survey command was sent: the vehicle was never retargeted.</em></p>"
    rows = []
    for s in items:
        if not isinstance(s, Mapping):
            continue
        a = s.get("asked") or {}
        c = s.get("candidate") or {}
        t = s.get("truth") or {}
        what = f"{a.get('kind', '?')} from {_pos(a.get('x'), a.get('y'))}"
        if a.get("length") is not None:
            what += f", {_num(a.get('length'))} m at {_num(a.get('heading'))}°"
        if c:
            what += f", over {_pos(c.get('x'), c.get('y'))}"
        state = str(s.get("final_state", "?")) + (f": {s.get('text')}" if s.get("text") else "")
        flown = ("not flown" if t.get("set_off_s") is None else
                 f"set off {_num(t.get('set_off_s'))} s, done {_num(t.get('completed_s'))} s"
                 + (f", stopped {_num(t.get('stopped_s'))} s" if t.get("stopped_s") is not None else ""))
        rows.append(f"<tr><td class='r'>{_num(s.get('id'))}</td><td>{_e(what)}</td>"
                    f"<td class='r'>{_num(s.get('sent_at_s'))}</td><td class='r'>{_num(s.get('accepted_at_s'))}</td>"
                    f"<td class='r'>{_num(s.get('started_at_s'))}</td><td class='r'>{_num(s.get('completed_at_s'))}</td>"
                    f"<td>{_e(state)}</td><td class='r'>{_num(t.get('received_by_vehicle_s'))}</td>"
                    f"<td>{_e(flown)}</td></tr>")
    return ('<h3>Survey commands</h3><p class="note">The camera pass as it crossed the acoustic link: each '
            "survey command topside sent, when the vehicle's answers reached topside (dive seconds; "
            "started and completed are the vehicle's stamps), and, from the simulation, when the command "
            'reached the vehicle and when the vehicle flew it.</p><table class="surveys"><tr><th>survey</th>'
            "<th>asked</th><th>sent (s)</th><th>accepted (s)</th><th>started (s)</th><th>completed (s)</th>"
            "<th>final state topside</th><th>reached the vehicle (s)</th><th>flown (truth)</th></tr>"
            + "".join(rows) + "</table>")


def _thumb_src(path: Path) -> tuple[str | None, bool]:
    """A data URI of a thumbnail of ``path`` (about 200 px wide) and whether it is upscaled."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            im.load()
            w = im.width
            if w <= 400:
                data = path.read_bytes()
                if path.suffix.lower() != ".png":
                    buf = io.BytesIO()
                    im.convert("RGB").save(buf, format="PNG")
                    data = buf.getvalue()
                return "data:image/png;base64," + base64.b64encode(data).decode("ascii"), w < 200
            small = im.convert("RGB")
            small.thumbnail((200, 200 * im.height // max(w, 1) + 1))
            buf = io.BytesIO()
            small.save(buf, format="JPEG", quality=85)
            return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii"), False
    except Exception:
        return None, False


def _gallery(out: Path, images: Sequence[Mapping[str, Any]]) -> str:
    """Thumbnails of received images: confirming and requested ones first, then by time."""
    if not images:
        return "<p><em>No images were received.</em></p>"

    def key(m: Mapping[str, Any]) -> tuple[int, float]:
        rank = 0 if m.get("confirms") else 1 if m.get("requested") else 2
        return rank, _f(m.get("time_s")) or 0.0

    ordered = sorted(images, key=key)
    shown, left = ordered[:GALLERY_CAP], len(ordered) - GALLERY_CAP
    n_conf = sum(1 for m in images if m.get("confirms"))
    n_req = sum(1 for m in images if m.get("requested"))
    cards = []
    for m in shown:
        file = str(m.get("file", ""))
        src, small = _thumb_src(out / file) if file else (None, False)
        cls = "card conf" if m.get("confirms") else "card req" if m.get("requested") else "card"
        pix = ' style="image-rendering:pixelated"' if small else ""
        img = (f'<a href="{_e(file)}"><img src="{src}" alt="image {_e(m.get("image_id", "?"))}"{pix}></a>'
               if src else '<div class="missing">image file missing</div>')
        caption = " \u00b7 ".join([
            f"image {m.get('image_id', '?')}",
            f"{_num(m.get('time_s'))} s",
            _pos(m.get("x"), m.get("y"), ".0f"),
            f"{_num(m.get('bytes'), ',.0f')} B",
            f"{_num(m.get('layers'))} layers",
        ])
        flags = ""
        if m.get("confirms"):
            flags += f'<div class="flag conf">confirms {_e(m["confirms"])}</div>'
        if m.get("requested"):
            flags += '<div class="flag req">requested</div>'
        cards.append(f'<figure class="{cls}">{img}<figcaption>{_e(caption)}{flags}</figcaption></figure>')
    head = (f"<p>{len(images)} image(s) received; {n_conf} confirm a target, {n_req} were requested by "
            "the operator. Confirming and requested images come first (green border: confirms a "
            "target). Positions are the vehicle's (x, y) in metres; bytes are those sent over the link.")
    if left > 0:
        head += f" Showing {GALLERY_CAP}; {left} more are not shown (all are in <code>images/</code>)."
    return head + f'</p><div class="gallery">{"".join(cards)}</div>'


def _regions_section(out: Path, regions: Sequence[Mapping[str, Any]]) -> str:
    """The image regions asked during the dive: what was asked, how the vehicle served it (a
    crop: the region coded on its own and pasted over the image; or the image's packets) and
    its bytes, with the image as shown topside (the region outlined) and the crop itself."""
    if not regions:
        return ('<h3 id="regions">Image regions</h3><p class="note">No image region was asked for: no '
                "image showed an object too blurry to tell.</p>")
    rows, cards = [], []
    for r in regions:
        goal = r.get("goal") or {}
        unit = {"quality": " dB", "layer": " layers", "bytes": " B"}.get(str(goal.get("kind")), "")
        x0, y0, x1, y1 = r["box"]
        crop = r.get("crop")
        how = "-"
        if r.get("served") == "crop" and crop:
            how = (f"crop {crop['width']} x {crop['height']} px (image {crop['image_id']}), "
                   f"{_num(crop['held_bytes'], ',.0f')} of {_num(crop['total_bytes'], ',.0f')} B"
                   + (", shown over the image" if crop.get("shown") else ", the image as good there by now"))
        elif r.get("served") == "packets":
            how = f"the image's packets, {_num(r.get('bytes'), ',.0f')} B"
        rows.append(
            f"<tr><td class='r'>{_num(r.get('asked_s'))}</td><td>{_e(r.get('by', ''))}</td>"
            f"<td class='r'>{_e(r['image_id'])}</td><td>x {x0}..{x1}, y {y0}..{y1} ({x1 - x0} x {y1 - y0} px)</td>"
            f"<td>{_e(goal.get('value'))}{unit}</td><td>{_e(r.get('state', ''))}</td><td>{_e(how)}</td>"
            f"<td class='r'>{_num(r.get('bytes'), ',.0f')}</td>"
            f"<td class='r'>{_num(r.get('layers_complete'))} of {_num(r.get('layers'))}</td>"
            f"<td class='r'>{_num(r.get('image_bytes'), ',.0f')}</td></tr>")
        for key, label in (("file", f"image {r['image_id']} as shown, region outlined"),
                           ("crop_file", "the crop")):
            file = r.get(key)
            src, small = _thumb_src(out / str(file)) if file else (None, False)
            if src:
                pix = ' style="image-rendering:pixelated"' if small else ""
                cards.append(f'<figure class="card"><a href="{_e(file)}"><img src="{src}" alt="{_e(label)}"{pix}></a>'
                             f"<figcaption>{_e(label)} (command {r['command_id']})</figcaption></figure>")
    return ('<h3 id="regions">Image regions</h3><p class="note">Regions of images the operator asked to see '
            "sharper (around an object too blurry to tell). The vehicle serves each the cheaper way it "
            "measures: a crop (the region coded on its own as the difference to what topside holds, "
            "pasted over the image) or the image's own packets. Bytes: the crop's body, or the region's "
            "packets, that arrived; the image's bytes are all it holds. Asked at dive seconds.</p>"
            '<table class="regions"><tr><th>asked (s)</th><th>by</th><th>image</th><th>region</th>'
            "<th>goal</th><th>answer</th><th>served as</th><th>bytes</th><th>layers inside</th>"
            "<th>image bytes</th></tr>" + "".join(rows) + "</table>"
            + (f'<div class="gallery">{"".join(cards)}</div>' if cards else ""))


def _decisions_table(decisions: Sequence[Mapping[str, Any]]) -> str:
    """Every decision in time order; rows by a person highlighted."""
    if not decisions:
        return "<p><em>No decisions were recorded.</em></p>"
    rows = []
    for d in sorted(decisions, key=lambda d: _f(d.get("t")) or 0.0):
        who = str(d.get("who", ""))
        cls = f' class="who-{_e(who)}"' if who in ("person", "script", "system") else ""
        rows.append(f"<tr{cls}><td class='r'>{_num(d.get('t'))}</td><td>{_e(who)}</td>"
                    f"<td>{_e(d.get('kind', ''))}</td><td>{_e(d.get('text', ''))}</td></tr>")
    n_person = sum(1 for d in decisions if d.get("who") == "person")
    note = (f"<p>{len(decisions)} decision(s); {n_person} taken by a person (highlighted), the rest by the "
            "operator script or the system.</p>")
    return (note + '<div class="scroll"><table class="decisions"><tr><th>time (s)</th><th>who</th>'
            "<th>kind</th><th>what</th></tr>" + "".join(rows) + "</table></div>")


_CSS = """
body{font-family:Helvetica,Arial,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;
 color:#222;line-height:1.45;font-size:15px}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ddd;padding-bottom:.15em;margin-top:1.8em}
.sub{color:#555;margin-top:0}.nav{font-size:.9em;color:#666}.nav a{color:#2a6ebb;margin-right:.8em}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:4px 9px;vertical-align:top}
th{background:#f2f2f2;text-align:left;font-weight:600}td.r{text-align:right;font-variant-numeric:tabular-nums}
td.c{text-align:center}.met{color:#fff;background:#2e8b3a;padding:1px 6px;border-radius:3px;font-weight:bold}
.notmet{color:#fff;background:#c62828;padding:1px 6px;border-radius:3px;font-weight:bold;white-space:nowrap}.na{color:#888}
.bad{color:#c62828;font-weight:bold}.ok{color:#2e8b3a;font-weight:bold}table.false th{background:#fde8e8}
.summary{font-size:1.05em;background:#f7f9fc;border-left:4px solid #2a6ebb;padding:.6em 1em}
.gallery{display:flex;flex-wrap:wrap;gap:10px}.card{margin:0;width:204px;border:1px solid #ccc;padding:3px;
 background:#fafafa}.card img{width:200px;display:block}.card.conf{border:4px solid #2e8b3a;padding:1px}
.card.req{border:2px solid #2a6ebb;padding:2px}.card.conf.req{border:4px solid #2e8b3a}
figcaption{font-size:11.5px;color:#333;margin-top:3px}.flag{font-weight:bold;font-size:12px}
.flag.conf{color:#2e8b3a}.flag.req{color:#2a6ebb}.missing{width:200px;height:120px;background:#eee;color:#888;
 display:flex;align-items:center;justify-content:center;font-size:12px}
.scroll{max-height:640px;overflow:auto;border:1px solid #eee}table.decisions{margin:0;width:100%}
tr.who-person td{background:#fff3c4;font-weight:600}tr.who-system td{color:#666}
.fig{margin:1em 0}pre{background:#f6f6f6;padding:8px;overflow:auto;font-size:12px}
details summary{cursor:pointer;font-weight:600}.note{color:#555;font-size:.92em}
"""


def _link_note(metrics: Mapping[str, Any]) -> str:
    """One paragraph on how the vehicle used its link: fill, spare and redundant bytes, request
    to first answer, the map ten minutes after the survey."""
    link = metrics.get("link") or {}
    parts = []
    if _f(link.get("fill")) is not None:
        parts.append(f"vehicle link use {float(link['fill']):.0%} of the packets it sent")
    if _f(link.get("fill_with_work")) is not None:
        parts.append(f"{float(link['fill_with_work']):.0%} while work was ready")
    if _f(link.get("spare_bytes")) is not None:
        parts.append(f"{int(link['spare_bytes']):,} B of spare work (re-sends, provisional subgrids, further "
                     f"image layers, refinements) and {int(link.get('redundant_bytes') or 0):,} B of redundant "
                     "copies of acks, commands and first answers")
    if _f(link.get("frame_loss")) is not None:
        parts.append(f"frame loss {float(link['frame_loss']):.0%}")
    resp = metrics.get("responses") or {}
    if resp.get("requests"):
        med = resp.get("median_vehicle_slots")
        parts.append(f"{resp['requests']} requests, first answer "
                     + ("never, in the median" if med is None else f"after {med:g} vehicle slot(s) in the median")
                     + f" ({float(resp.get('at_next_vehicle_slot') or 0):.0%} at the next vehicle slot)")
    cov = metrics.get("map_coverage_after_survey") or {}
    if cov:
        parts.append("map ten minutes after the survey: " + ", ".join(
            f"level {k} {float(v):.1%}" for k, v in sorted(cov.items(), key=lambda kv: int(kv[0]))))
    return f'<p class="note">Link: {_e("; ".join(parts))}.</p>' if parts else ""


def write_report(
    out: Path,
    metrics: Mapping[str, Any],
    *,
    charts: Sequence[str],
    maps: Sequence[str],
    images: Sequence[Mapping[str, Any]],
    decisions: Sequence[Mapping[str, Any]],
    regions: Sequence[Mapping[str, Any]] = (),
) -> Path:
    """Write ``out/report.html`` (one self-contained file) and return its path.

    ``charts`` and ``maps`` are SVG/HTML fragments (from :func:`line_chart`, :func:`timeline_chart`,
    :func:`map_figure`), ``images`` one dict per received image (``file`` relative to ``out``),
    ``decisions`` dicts with ``t``, ``kind``, ``text`` and ``who``, ``regions`` the image
    regions asked (see ``outcome._regions``).
    """
    out = Path(out)
    sc_line = _scenario_line(metrics.get("scenario"))
    summary = metrics.get("summary")
    summary_html = f'<p class="summary">{_e(summary)}</p>' if summary else ""
    facts = []
    for key, label, unit in (("dive_seconds", "dive length", " s"), ("survey_end_s", "survey ended at", " s"),
                             ("images_received", "images received", ""),
                             ("images_captured", "images taken", "")):
        if _f(metrics.get(key)) is not None:
            facts.append(f"{label} {_num(metrics.get(key), ',.0f')}{unit}")
    facts_html = f'<p class="note">{_e(" · ".join(facts))}</p>' if facts else ""
    link_html = _link_note(metrics)
    maps_html = "".join(f'<div class="fig">{m}</div>' for m in maps) or "<p><em>No map was received.</em></p>"
    charts_html = "".join(f'<div class="fig">{c}</div>' for c in charts) or "<p><em>No charts.</em></p>"
    doc = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width,initial-scale=1">
<title>CoEx demo report</title><style>{_CSS}</style></head><body>
<h1>CoEx demo: nested survey over a simulated acoustic link</h1>
<p class="sub">{_e(sc_line)}</p>
<p class="nav"><a href="#outcome">Outcome</a><a href="#map">Map</a><a href="#images">Images</a>
<a href="#vehicles">Vehicles</a><a href="#time">The dive over time</a><a href="#decisions">Decisions</a><a href="#raw">Raw metrics</a></p>
<h2 id="outcome">Outcome</h2>
<p class="note">{_e(WHO_SEES_WHAT)}</p>
{summary_html}{facts_html}
<h3>Goals</h3>
{_goals_table(metrics.get("goals"))}
<h3>Targets</h3>
<p class="note">Identifiable at 1 m: when the 1 m map held topside first showed the target. Confirmed at:
when a received image showing it was accepted; TDMA cycles are counted from the image request.
Decision time: from identifiable at 1 m to the confirming image.</p>
{_targets_table(metrics.get("targets"))}
{_false_table(metrics.get("false_confirmations"))}
<h3>Detections</h3>
<p class="note">What the vehicle's own detectors found in its full-resolution data and sent as
suggestions (the operator decides), judged here against the truth.</p>
{_detections_table(metrics.get("detections"), metrics.get("detection_cost"), metrics.get("targets"))}
{_navigation_section(metrics.get("navigation"))}
<h2 id="map">Map</h2>
<p class="note">The bathymetry as received topside, finest level first. Colour is depth (with light
hillshading from the north-west); hatched grey areas hold no data. Red squares are the true targets,
orange diamonds decoys, cyan circles the candidates the operator flagged in the received map
(filled once imaged), magenta triangles the vehicle's detections.</p>
{maps_html}
<h2 id="images">Images</h2>
{_gallery(out, images)}
{_regions_section(out, regions)}
{_vehicles_section(metrics.get("vehicles"))}
<h2 id="time">The dive over time</h2>
{link_html}
{charts_html}
{_surveys_table(metrics.get("surveys"))}
<h2 id="decisions">Decisions</h2>
{_decisions_table(decisions)}
<h2 id="raw">Raw metrics</h2>
<details><summary>Raw metrics (metrics.json)</summary><pre>{_e(json.dumps(metrics, indent=2, default=str))}</pre></details>
</body></html>
"""
    path = out / "report.html"
    path.write_text(doc, encoding="utf-8")
    return path
