"""Drone file formats of a flight plan: QGroundControl .plan, QGC WPL 110, DJI WPML .kmz, KML.

Every writer takes one :class:`~pipeline.flightplan.mission.Sortie` of a
:class:`~pipeline.flightplan.mission.FlightPlan` and writes WGS84 coordinates.
Heights, by file (docs/flightplans.md):

========================  =============================  ==========================================
file                      ``takeoff`` (default)          ``amsl`` / ``ellipsoid``
========================  =============================  ==========================================
``.plan``, ``.waypoints``  frame 3, relative to home      frame 0 (MAVLink "MSL"): DSM-datum heights
``.kmz`` (DJI WPML)        ``relativeToStartPoint``       amsl: ``relativeToStartPoint``;
                                                          ellipsoid: ``WGS84`` ellipsoidal heights
``.kml``                   ``absolute``: DSM-datum        same
========================  =============================  ==========================================

MAVLink has no ellipsoid frame and DJI's executable waylines accept only
ellipsoidal or take-off-relative heights, hence the table.

Lidar recording in MAVLink files: ``MAV_CMD_DO_SET_CAM_TRIGG_DIST`` (206) with
a 1 m distance and "trigger once now" at each lane start, distance 0 at its end,
as QGroundControl's own survey items do per transect; lidar kits log those
trigger events (or start recording on them). DJI: ``recordPointCloud`` actions
(``startRecord`` / ``stopRecord``) at the lane ends.
"""

from __future__ import annotations

import json
import os
import time
import zipfile
from pathlib import Path
from xml.sax.saxutils import escape

from ..errors import OutputError
from ..flightplan.mission import FlightPlan, Sortie, Waypoint

__all__ = ["plan_json", "write_kml", "write_kmz", "write_plan", "write_waypoints"]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_DO_SET_CAM_TRIGG_DIST = 206
MAV_FRAME_GLOBAL = 0  # altitude above mean sea level
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
TRIGGER_DISTANCE_M = 1.0
WPML_NS = "http://www.dji.com/wpmz/1.0.2"


#: DJI WPML turn mode of every waypoint: pass through it on a continuous-curvature path,
#: never stop (a stop per waypoint doubles the time of a lane and shakes the lidar).
WPML_TURN_MODE = "toPointAndPassWithContinuityCurvature"


def _frame(plan: FlightPlan) -> int:
    return MAV_FRAME_GLOBAL_RELATIVE_ALT if plan.altitude_reference == "takeoff" else MAV_FRAME_GLOBAL


def _mavlink_altitude(plan: FlightPlan, w: Waypoint) -> float:
    """Relative to home (frame 3) or the DSM datum taken as MSL (frame 0)."""
    return w.altitude_m if plan.altitude_reference == "takeoff" else w.height_m


def _mission_items(plan: FlightPlan, sortie: Sortie) -> list[tuple[int, int, list[float | None]]]:
    """(command, frame, seven params) of every mission item after the home point."""
    frame, p = _frame(plan), plan.params
    items: list[tuple[int, int, list[float | None]]] = []
    for w in sortie.waypoints:
        alt = round(_mavlink_altitude(plan, w), 2)
        lat, lon = round(w.lat, 8), round(w.lon, 8)
        if "takeoff" in w.actions:
            items.append((MAV_CMD_NAV_TAKEOFF, frame, [0, 0, 0, None, lat, lon, alt]))
            items.append((MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, [1, p.transit_speed_m_s, -1, 0, 0, 0, 0]))
            continue
        if "home" in w.actions:
            items.append((MAV_CMD_NAV_WAYPOINT, frame, [0, 0, 0, None, lat, lon, alt]))
            items.append((MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0]))
            continue
        items.append((MAV_CMD_NAV_WAYPOINT, frame, [0, 0, 0, None, lat, lon, alt]))
        for action in w.actions:
            if action == "pattern_entry":
                items.append((MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, [1, p.speed_m_s, -1, 0, 0, 0, 0]))
            elif action == "lane_start":
                items.append((MAV_CMD_DO_SET_CAM_TRIGG_DIST, MAV_FRAME_MISSION, [TRIGGER_DISTANCE_M, 0, 1, 0, 0, 0, 0]))
            elif action == "lane_end":
                items.append((MAV_CMD_DO_SET_CAM_TRIGG_DIST, MAV_FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0]))
            elif action == "pattern_exit":
                items.append((MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, [1, p.transit_speed_m_s, -1, 0, 0, 0, 0]))
    return items


def plan_json(plan: FlightPlan, sortie: Sortie) -> dict:
    """The QGroundControl plan (simple items only) of one sortie, as a JSON-ready dict."""
    mode = 1 if plan.altitude_reference == "takeoff" else 2  # QGC: 1 relative, 2 AMSL
    items = []
    for i, (command, frame, params) in enumerate(_mission_items(plan, sortie), start=1):
        item = {
            "type": "SimpleItem",
            "command": command,
            "frame": frame,
            "autoContinue": True,
            "doJumpId": i,
            "params": params,
        }
        if frame != MAV_FRAME_MISSION:
            item.update({"Altitude": params[6], "AltitudeMode": mode, "AMSLAltAboveTerrain": None})
        items.append(item)
    return {
        "fileType": "Plan",
        "groundStation": "QGroundControl",
        "version": 1,
        "mission": {
            "version": 2,
            "firmwareType": 3,  # ArduPilot; QGC converts on load for PX4
            "vehicleType": 2,  # multirotor
            "cruiseSpeed": plan.params.transit_speed_m_s,
            "hoverSpeed": plan.params.speed_m_s,
            "globalPlanAltitudeMode": mode,
            "plannedHomePosition": [
                round(plan.home_lonlat[1], 8),
                round(plan.home_lonlat[0], 8),
                round(plan.home_ground_m, 2),
            ],
            "items": items,
        },
        "geoFence": {"version": 2, "circles": [], "polygons": []},
        "rallyPoints": {"version": 2, "points": []},
    }


def write_plan(path: str | os.PathLike, plan: FlightPlan, sortie: Sortie) -> Path:
    """Write a QGroundControl ``.plan`` (JSON; never NaN: JSON has no NaN, ``null`` instead)."""
    text = json.dumps(plan_json(plan, sortie), indent=1, allow_nan=False)
    return _write_text(path, text)


def write_waypoints(path: str | os.PathLike, plan: FlightPlan, sortie: Sortie) -> Path:
    """Write a QGC WPL 110 file: tab-separated, line 0 the home point (AMSL)."""
    lat, lon = plan.home_lonlat[1], plan.home_lonlat[0]
    lines = [
        "QGC WPL 110",
        _wpl_line(0, 1, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, [0, 0, 0, 0, lat, lon, plan.home_ground_m]),
    ]
    for i, (command, frame, params) in enumerate(_mission_items(plan, sortie), start=1):
        lines.append(_wpl_line(i, 0, frame, command, [0 if v is None else v for v in params]))
    return _write_text(path, "\n".join(lines) + "\n")


def _wpl_line(seq: int, current: int, frame: int, command: int, params: list[float]) -> str:
    values = [f"{v:.8f}" if k in (4, 5) else f"{v:.6g}" for k, v in enumerate(params)]
    return "\t".join([str(seq), str(current), str(frame), str(command), *values, "1"])


def write_kml(path: str | os.PathLike, plan: FlightPlan, sortie: Sortie) -> Path:
    """Write a KML for Google Earth / UgCS / GIS: route and lanes, ``altitudeMode`` absolute.

    KML heights are above mean sea level; the DSM-datum heights are written.
    """
    route = " ".join(f"{w.lon:.8f},{w.lat:.8f},{w.height_m:.2f}" for w in sortie.waypoints)
    marks = [
        "<Placemark><name>route</name><styleUrl>#route</styleUrl><LineString>"
        f"<altitudeMode>absolute</altitudeMode><coordinates>{route}</coordinates></LineString></Placemark>"
    ]
    waypoints = sortie.waypoints
    for a, b in zip(waypoints, waypoints[1:]):
        if "lane_start" in a.actions or ("terrain" in a.actions and "lane_end" not in a.actions):
            marks.append(
                f"<Placemark><name>pattern {a.pattern_id} lane {a.lane_index}</name><styleUrl>#lane</styleUrl>"
                f"<LineString><altitudeMode>absolute</altitudeMode><coordinates>{a.lon:.8f},{a.lat:.8f},"
                f"{a.height_m:.2f} {b.lon:.8f},{b.lat:.8f},{b.height_m:.2f}</coordinates></LineString></Placemark>"
            )
    for w in waypoints:
        marks.append(
            f"<Placemark><name>{w.sequence}</name><description>{escape(', '.join(w.actions))}</description>"
            f"<styleUrl>#waypoint</styleUrl><Point><altitudeMode>absolute</altitudeMode>"
            f"<coordinates>{w.lon:.8f},{w.lat:.8f},{w.height_m:.2f}</coordinates></Point></Placemark>"
        )
    text = (
        '<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2"><Document>'
        f"<name>holefill re-flight, sortie {sortie.number}</name>"
        "<description>Heights above mean sea level (the DSM's vertical datum).</description>"
        '<Style id="route"><LineStyle><color>ff00a5ff</color><width>2</width></LineStyle></Style>'
        '<Style id="lane"><LineStyle><color>ff0000ff</color><width>4</width></LineStyle></Style>'
        '<Style id="waypoint"><IconStyle><scale>0.5</scale></IconStyle></Style>'
        + "".join(marks)
        + "</Document></kml>\n"
    )
    return _write_text(path, text)


def write_kmz(path: str | os.PathLike, plan: FlightPlan, sortie: Sortie, *, drone_enum: int, payload_enum: int) -> Path:
    """Write a DJI WPML ``.kmz`` (wpmz/template.kml + wpmz/waylines.wpml) for DJI Pilot 2.

    The take-off point itself is not a waypoint (the aircraft takes off where it
    is); waypoint indices run 0, 1, 2, ... without gaps.
    """
    points = [w for w in sortie.waypoints if "takeoff" not in w.actions]
    ellipsoid = plan.altitude_reference == "ellipsoid"
    heights = [w.altitude_m if ellipsoid else w.height_m - plan.home_ground_m for w in points]
    config = _mission_config(plan, points, heights, drone_enum, payload_enum)
    template_marks, wayline_marks = [], []
    group = 0
    for index, (w, h) in enumerate(zip(points, heights)):
        actions, group = _wpml_actions(w, index, group)
        template_marks.append(_placemark(w, index, h, plan, template=True, actions=actions))
        wayline_marks.append(_placemark(w, index, h, plan, template=False, actions=actions))
    distance = sortie.length_m
    mode = "WGS84" if ellipsoid else "relativeToStartPoint"
    now = int(time.time() * 1000)
    template = (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2" xmlns:wpml="{WPML_NS}">'
        f"<Document><wpml:author>holefill</wpml:author><wpml:createTime>{now}</wpml:createTime>"
        f"<wpml:updateTime>{now}</wpml:updateTime>{config}<Folder>"
        "<wpml:templateType>waypoint</wpml:templateType><wpml:templateId>0</wpml:templateId>"
        "<wpml:waylineCoordinateSysParam><wpml:coordinateMode>WGS84</wpml:coordinateMode>"
        f"<wpml:heightMode>{'EGM96' if ellipsoid else 'relativeToStartPoint'}</wpml:heightMode>"
        "</wpml:waylineCoordinateSysParam>"
        f"<wpml:autoFlightSpeed>{plan.params.transit_speed_m_s:g}</wpml:autoFlightSpeed>"
        "<wpml:gimbalPitchMode>usePointSetting</wpml:gimbalPitchMode>"
        "<wpml:globalWaypointHeadingParam><wpml:waypointHeadingMode>followWayline</wpml:waypointHeadingMode>"
        "</wpml:globalWaypointHeadingParam>"
        f"<wpml:globalWaypointTurnMode>{WPML_TURN_MODE}</wpml:globalWaypointTurnMode>"
        "<wpml:globalUseStraightLine>1</wpml:globalUseStraightLine>"
        f"{''.join(template_marks)}</Folder></Document></kml>\n"
    )
    waylines = (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2" xmlns:wpml="{WPML_NS}">'
        f"<Document>{config}<Folder><wpml:templateId>0</wpml:templateId>"
        f"<wpml:executeHeightMode>{mode}</wpml:executeHeightMode><wpml:waylineId>0</wpml:waylineId>"
        f"<wpml:distance>{distance:.1f}</wpml:distance><wpml:duration>{sortie.duration_s:.0f}</wpml:duration>"
        f"<wpml:autoFlightSpeed>{plan.params.transit_speed_m_s:g}</wpml:autoFlightSpeed>"
        f"{''.join(wayline_marks)}</Folder></Document></kml>\n"
    )
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.writestr("wpmz/template.kml", template)
            archive.writestr("wpmz/waylines.wpml", waylines)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write: {e}") from None
    return path


def _mission_config(plan: FlightPlan, points: list[Waypoint], heights: list[float], drone: int, payload: int) -> str:
    first = heights[0] - (plan.home_ground_m if plan.altitude_reference == "ellipsoid" else 0.0)
    safe_height = min(1500.0, max(2.0, first))
    return (
        "<wpml:missionConfig><wpml:flyToWaylineMode>safely</wpml:flyToWaylineMode>"
        "<wpml:finishAction>goHome</wpml:finishAction><wpml:exitOnRCLost>executeLostAction</wpml:exitOnRCLost>"
        "<wpml:executeRCLostAction>goBack</wpml:executeRCLostAction>"
        f"<wpml:takeOffSecurityHeight>{safe_height:.1f}</wpml:takeOffSecurityHeight>"
        f"<wpml:globalTransitionalSpeed>{plan.params.transit_speed_m_s:g}</wpml:globalTransitionalSpeed>"
        f"<wpml:globalRTHHeight>{max(heights) - (plan.home_ground_m if plan.altitude_reference == 'ellipsoid' else 0.0):.1f}"
        "</wpml:globalRTHHeight>"
        f"<wpml:droneInfo><wpml:droneEnumValue>{drone}</wpml:droneEnumValue>"
        "<wpml:droneSubEnumValue>0</wpml:droneSubEnumValue></wpml:droneInfo>"
        f"<wpml:payloadInfo><wpml:payloadEnumValue>{payload}</wpml:payloadEnumValue>"
        "<wpml:payloadSubEnumValue>0</wpml:payloadSubEnumValue>"
        "<wpml:payloadPositionIndex>0</wpml:payloadPositionIndex></wpml:payloadInfo></wpml:missionConfig>"
    )


def _wpml_actions(w: Waypoint, index: int, group: int) -> tuple[str, int]:
    """The action group of one waypoint (gimbal nadir at the first, record at lane ends)."""
    actions = []
    if index == 0:
        actions.append(
            (
                "gimbalRotate",
                "<wpml:gimbalRotateMode>absoluteAngle</wpml:gimbalRotateMode>"
                "<wpml:gimbalPitchRotateEnable>1</wpml:gimbalPitchRotateEnable>"
                "<wpml:gimbalPitchRotateAngle>-90</wpml:gimbalPitchRotateAngle>"
                "<wpml:gimbalRollRotateEnable>0</wpml:gimbalRollRotateEnable>"
                "<wpml:gimbalRollRotateAngle>0</wpml:gimbalRollRotateAngle>"
                "<wpml:gimbalYawRotateEnable>0</wpml:gimbalYawRotateEnable>"
                "<wpml:gimbalYawRotateAngle>0</wpml:gimbalYawRotateAngle>"
                "<wpml:gimbalRotateTimeEnable>0</wpml:gimbalRotateTimeEnable>"
                "<wpml:gimbalRotateTime>0</wpml:gimbalRotateTime>"
                "<wpml:payloadPositionIndex>0</wpml:payloadPositionIndex>",
            )
        )
    for action in w.actions:
        if action in ("lane_start", "lane_end"):
            operate = "startRecord" if action == "lane_start" else "stopRecord"
            actions.append(
                (
                    "recordPointCloud",
                    f"<wpml:recordPointCloudOperate>{operate}</wpml:recordPointCloudOperate>"
                    "<wpml:payloadPositionIndex>0</wpml:payloadPositionIndex>",
                )
            )
    if not actions:
        return "", group
    body = "".join(
        f"<wpml:action><wpml:actionId>{k}</wpml:actionId><wpml:actionActuatorFunc>{func}</wpml:actionActuatorFunc>"
        f"<wpml:actionActuatorFuncParam>{params}</wpml:actionActuatorFuncParam></wpml:action>"
        for k, (func, params) in enumerate(actions)
    )
    xml = (
        f"<wpml:actionGroup><wpml:actionGroupId>{group}</wpml:actionGroupId>"
        f"<wpml:actionGroupStartIndex>{index}</wpml:actionGroupStartIndex>"
        f"<wpml:actionGroupEndIndex>{index}</wpml:actionGroupEndIndex>"
        "<wpml:actionGroupMode>sequence</wpml:actionGroupMode>"
        "<wpml:actionTrigger><wpml:actionTriggerType>reachPoint</wpml:actionTriggerType></wpml:actionTrigger>"
        f"{body}</wpml:actionGroup>"
    )
    return xml, group + 1


def _placemark(w: Waypoint, index: int, height: float, plan: FlightPlan, *, template: bool, actions: str) -> str:
    leaving_pattern = any(a in w.actions for a in ("pattern_exit", "home"))
    speed = plan.params.transit_speed_m_s if leaving_pattern else plan.params.speed_m_s
    head = (
        f"<Placemark><Point><coordinates>{w.lon:.8f},{w.lat:.8f}</coordinates></Point><wpml:index>{index}</wpml:index>"
    )
    if template:
        ellipsoid = (
            f"<wpml:ellipsoidHeight>{height:.2f}</wpml:ellipsoidHeight>"
            if plan.altitude_reference == "ellipsoid"
            else ""
        )
        shown = w.height_m if plan.altitude_reference == "ellipsoid" else height
        return (
            f"{head}{ellipsoid}<wpml:height>{shown:.2f}</wpml:height><wpml:useGlobalHeight>0</wpml:useGlobalHeight>"
            f"<wpml:useGlobalSpeed>0</wpml:useGlobalSpeed><wpml:waypointSpeed>{speed:g}</wpml:waypointSpeed>"
            "<wpml:useGlobalHeadingParam>1</wpml:useGlobalHeadingParam><wpml:useGlobalTurnParam>1</wpml:useGlobalTurnParam>"
            f"<wpml:gimbalPitchAngle>-90</wpml:gimbalPitchAngle>{actions}</Placemark>"
        )
    return (
        f"{head}<wpml:executeHeight>{height:.2f}</wpml:executeHeight><wpml:waypointSpeed>{speed:g}</wpml:waypointSpeed>"
        "<wpml:waypointHeadingParam><wpml:waypointHeadingMode>followWayline</wpml:waypointHeadingMode>"
        "</wpml:waypointHeadingParam><wpml:waypointTurnParam>"
        f"<wpml:waypointTurnMode>{WPML_TURN_MODE}</wpml:waypointTurnMode>"
        "<wpml:waypointTurnDampingDist>0</wpml:waypointTurnDampingDist></wpml:waypointTurnParam>"
        f"<wpml:gimbalPitchAngle>-90</wpml:gimbalPitchAngle>{actions}</Placemark>"
    )


def _write_text(path: str | os.PathLike, text: str) -> Path:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write: {e}") from None
    return path
