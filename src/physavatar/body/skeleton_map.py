"""Which joint of a motion-capture skeleton drives which Anny bone: found from joint names and the
skeleton's structure, with the reason for every choice (``physavatar motion inspect`` prints them).

Names. A joint name is cut into lower-case words (camelCase, ``_ . - :`` and spaces;
``mixamorig:``, ``Character1_``, ``Bip01 ``-style prefixes dropped), a side is read from
``Left``/``Right``/``L``/``R`` words (``LeftUpLeg``, ``UpperLeg_L``, ``thigh.L``, ``l_hip``,
``Bip01 L Thigh``, ``lhand``), and the remaining words name a body part through synonyms
(``_PARTS``): UpLeg / UpperLeg / Thigh / Hip / femur; Leg / LowerLeg / Shin / Knee / Calf / tibia;
Foot / Ankle; Toe / ToeBase; Collar / Clavicle; Shoulder; Arm / UpperArm / humerus; ForeArm /
LowerArm / Elbow / radius; Hand / Wrist; Hips / Pelvis; Spine / Chest / LowerBack / Torso …; Neck;
Head. Fingers, toes' ends, twist/roll helpers and end joints are left unmapped.

Structure. Along each limb the parts are put in order from the body outwards, which settles what
names alone cannot: the upper of two "hip"-like joints of a leg (CMU's ``LHipJoint`` above
``LeftHip``) is the pelvis side, the lower of Ankle/Foot (SMPL's ``L_Foot``) is the toe, and a
``Shoulder`` is the clavicle when an ``Arm`` follows it (Mixamo) but the upper arm when it follows a
``Collar`` (CMU, SMPL). A limb joint whose name says nothing, between two that do, takes the part
in between. The hips are the joint named Hips/Pelvis above both legs, else the joint the two legs
branch from (so a ground or reference root above the hips is skipped). The joints from the hips
to the head are split at the first neck joint: the spine joint the arms branch from (or the last
one below the neck) drives Anny's upper chest ``spine01``, the others the Anny spine bones at the
nearest fraction of the hips-to-chest length, and neck joints Anny's neck bones the same way.

When the names give no legs at all, :func:`structural_map` maps the skeleton from its shape alone
(mirror branches for legs and arms, segment lengths along each limb; see there).

A ``--mapping`` JSON ``{joint: anny_bone}`` overrides any of this (``""`` un-maps a joint).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

# Body part words (side words, digits and prefixes removed, the rest joined) -> part.
_PARTS = {
    "hipjoint": "pelvis", "pelvisside": "pelvis",
    "upleg": "upperleg", "upperleg": "upperleg", "thigh": "upperleg", "femur": "upperleg", "legupper": "upperleg",
    "uleg": "upperleg", "hip": "upperleg",  # "hip" with a side; without one it is the hips
    "leg": "lowerleg", "lowerleg": "lowerleg", "shin": "lowerleg", "knee": "lowerleg", "calf": "lowerleg",
    "tibia": "lowerleg", "leglower": "lowerleg", "lleg": "lowerleg",
    "foot": "foot", "ankle": "foot",
    "toe": "toe", "toes": "toe", "toebase": "toe", "ball": "toe",
    "collar": "clavicle", "clavicle": "clavicle", "clav": "clavicle", "collarbone": "clavicle",
    "shoulder": "shoulder",
    "arm": "upperarm", "upperarm": "upperarm", "humerus": "upperarm", "armupper": "upperarm", "uparm": "upperarm",
    "forearm": "forearm", "lowerarm": "forearm", "elbow": "forearm", "radius": "forearm", "armlower": "forearm",
    "hand": "hand", "wrist": "hand",
    "hips": "hips", "pelvis": "hips",
    "spine": "spine", "chest": "spine", "upperchest": "spine", "lowerback": "spine", "back": "spine",
    "abdomen": "spine", "torso": "spine", "waist": "spine", "thorax": "spine", "lowerspine": "spine",
    "upperspine": "spine", "spinelower": "spine", "spineupper": "spine", "spinemid": "spine", "belly": "spine",
    "neck": "neck", "lowerneck": "neck", "upperneck": "neck", "neckbase": "neck",
    "head": "head",
}
_SIDE_WORDS = {"left": "L", "l": "L", "lft": "L", "right": "R", "r": "R", "rt": "R", "rgt": "R"}
_PREFIX_WORDS = {"mixamorig", "character", "bip", "biped", "def", "org", "mch", "cc", "base", "armature", "rig",
                 "jnt", "joint", "bone", "sk", "b", "j", "skel", "skeleton", "smpl", "amass", "m", "mixamo"}
# words that make a joint a helper or a finger, never a body bone
_SKIP_WORDS = {"end", "nub", "roll", "twist", "top", "site", "ik", "pole", "target", "finger", "fingers", "thumb",
               "index", "middle", "ring", "pinky", "little", "jaw", "eye", "eyes", "tongue", "ear", "nose",
               "hair", "tail", "prop", "weapon", "ctrl", "helper", "dummy", "footsteps", "reference"}
_LEG = ("pelvis", "upperleg", "lowerleg", "foot", "toe")
_ARM = ("clavicle", "shoulder", "upperarm", "forearm", "hand")
_ANNY = {"pelvis": "pelvis", "upperleg": "upperleg01", "lowerleg": "lowerleg01", "foot": "foot",
         "clavicle": "clavicle", "upperarm": "upperarm01", "forearm": "lowerarm01", "hand": "wrist"}
_SPINE = ("spine05", "spine04", "spine03", "spine02")  # below the upper chest spine01
_NECK = ("neck01", "neck02", "neck03")


def name_words(name: str) -> list[str]:
    """Lower-case words of a joint name (namespace and rig prefixes dropped)."""
    n = re.split(r"[:|]", name)[-1]
    words = []
    for part in re.split(r"[\s_.\-]+", n):
        words += re.findall(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+", part)
    return [w.lower() for w in words if w.lower() not in _PREFIX_WORDS]


def classify(name: str) -> tuple[str | None, str | None, int | None, str]:
    """(side or None, part or None, number or None, words read) of one joint name."""
    words = name_words(name)
    side, number, rest = None, None, []
    for w in words:
        if w in _SIDE_WORDS and side is None:
            side = _SIDE_WORDS[w]
        elif w.isdigit():
            number = int(w) if number is None else number
        else:
            rest.append(w)
    if side is None:  # glued side letter: "lhand", "LeftArm" written "leftarm"
        for i, w in enumerate(rest):
            for pre, s in (("left", "L"), ("right", "R"), ("l", "L"), ("r", "R")):
                if w.startswith(pre) and w[len(pre):] in _PARTS and len(w) > len(pre):
                    side, rest[i] = s, w[len(pre):]
                    break
            if side:
                break
    said = " ".join(([{"L": "left", "R": "right"}[side]] if side else []) + rest)
    if not rest or any(w in _SKIP_WORDS for w in rest):
        return side, None, number, said
    part = _PARTS.get("".join(rest))
    if part is None and rest[-1] in _PARTS and len(rest) <= 2:  # e.g. "lower back" variants, "hip joint"
        part = _PARTS.get(rest[-1])
    if part == "upperleg" and "".join(rest) == "hip" and side is None:
        part = "hips"
    if part == "hips" and side is not None:
        part = "pelvis"  # a sided pelvis bone (Blender's pelvis.L)
    elif part in ("hips", "spine", "neck", "head"):
        side = None
    elif side is None and part is not None:
        part = None  # a limb part without a side cannot be placed by its name
    return side, part, number, said


@dataclass
class SkeletonMap:
    """joint index -> Anny bone, and a reason for every joint (mapped or not)."""

    names: list[str]
    bones: dict[int, str] = field(default_factory=dict)
    why: dict[int, str] = field(default_factory=dict)

    @property
    def by_bone(self) -> dict[str, int]:
        return {b: j for j, b in self.bones.items()}

    def table(self) -> list[tuple[str, str, str]]:
        """(joint, Anny bone or '-', reason) in the file's joint order."""
        return [(n, self.bones.get(j, "-"), self.why.get(j, "")) for j, n in enumerate(self.names)]


def _ancestors(j, parents):
    out = []
    p = parents[j]
    while p >= 0:
        out.append(p)
        p = parents[p]
    return out


def _depth(j, parents):
    return len(_ancestors(j, parents))


def _path(a, b, parents):
    """Joints strictly between ancestor a and descendant b."""
    out, p = [], parents[b]
    while p >= 0 and p != a:
        out.append(p)
        p = parents[p]
    return out[::-1] if p == a else None


def map_skeleton(names: list[str], parents, positions: np.ndarray, anny_rest: dict[str, np.ndarray],
                 explicit: dict[str, str] | None = None, first_frame: np.ndarray | None = None) -> SkeletonMap:
    """Map a skeleton's joints to Anny bones (see module doc).

    Args:
        names, parents: the skeleton ([J] names, [J] parent index or -1).
        positions: [J, 3] joint positions in some standing pose (used for lengths and fractions).
        anny_rest: Anny bone name -> rest head position (fractions along Anny's spine and neck).
        explicit: ``{joint name: anny bone or ""}`` applied last.
        first_frame: [J, 3] positions in the first frame (sides, when the names say nothing and
            the zero pose does not stand).
    """
    parents = np.asarray(parents)
    J = len(names)
    sm = SkeletonMap(list(names))
    info = [classify(n) for n in names]
    kids = {j: [k for k in range(J) if parents[k] == j] for j in range(J)}
    seg = lambda a, b: float(np.linalg.norm(positions[a] - positions[b]))

    for j, (side, part, _, said) in enumerate(info):
        sm.why[j] = f"name reads '{said}': not a body part" if part is None else f"name reads '{said}'"

    limb: dict[tuple[str, str], int] = {}  # (side, part) -> joint
    for side in ("L", "R"):
        for group, order in (("leg", _LEG), ("arm", _ARM)):
            cand = {p: sorted([j for j, (s, q, _, _) in enumerate(info) if s == side and q == p],
                              key=lambda j: _depth(j, parents)) for p in order}
            if group == "leg":
                ups = cand["upperleg"]
                below = cand["lowerleg"] + cand["foot"]
                if len(ups) > 1:  # the lowest "hip"-like joint above the knee is the thigh, the others pelvis
                    ref = below[0] if below else None
                    ups_ok = [u for u in ups if ref is None or u in _ancestors(ref, parents)] or ups
                    thigh = ups_ok[-1]
                    for u in ups:
                        if u != thigh and not cand["pelvis"]:
                            cand["pelvis"] = [u]
                            sm.why[u] += f"; the upper of two hip joints (above {names[thigh]!r}): the pelvis side"
                    cand["upperleg"] = [thigh]
                if len(cand["foot"]) > 1 and not cand["toe"]:
                    cand["toe"] = cand["foot"][1:2]
                    sm.why[cand["toe"][0]] += f"; below the ankle {names[cand['foot'][0]]!r}: the toes"
            else:
                for s in cand["shoulder"]:
                    if cand["upperarm"] and not cand["clavicle"]:
                        cand["clavicle"] = [s]
                        sm.why[s] += f"; an upper arm {names[cand['upperarm'][0]]!r} follows: the clavicle"
                    elif not cand["upperarm"]:
                        cand["upperarm"] = [s]
                        sm.why[s] += "; no separate upper-arm joint follows: the upper arm"
                if len(cand["hand"]) > 1:
                    for h in cand["hand"][1:]:
                        sm.why[h] += f"; below the wrist {names[cand['hand'][0]]!r}: left unmapped"
            for p in order:
                if cand.get(p):
                    limb[(side, p)] = cand[p][0]
            # structure: a limb joint between two named ones, named nothing useful
            seq = [p for p in order if p not in ("shoulder",)]
            for a, m, b in zip(seq, seq[1:], seq[2:]):
                if (side, a) in limb and (side, b) in limb and (side, m) not in limb:
                    between = _path(limb[(side, a)], limb[(side, b)], parents) or []
                    between = [k for k in between if seg(k, limb[(side, a)]) > 1e-9]
                    if between:
                        limb[(side, m)] = between[0]
                        sm.why[between[0]] += (f"; the joint between {names[limb[(side, a)]]!r} and "
                                               f"{names[limb[(side, b)]]!r}: the {m}")
            # structure: the first joint after the knee / elbow when the foot / hand has no usable name
            for a, b in (("lowerleg", "foot"), ("forearm", "hand")):
                if (side, a) in limb and (side, b) not in limb:
                    nxt = [k for k in kids[limb[(side, a)]] if info[k][1] is None and seg(k, limb[(side, a)]) > 1e-9]
                    if len(nxt) == 1:
                        limb[(side, b)] = nxt[0]
                        sm.why[nxt[0]] += f"; the only joint below {names[limb[(side, a)]]!r}: the {b}"

    for (side, p), j in limb.items():
        if p in _ANNY:
            sm.bones[j] = f"{_ANNY[p]}.{side}"

    # hips: a joint named hips/pelvis above both legs, else the joint the legs branch from
    legs = [limb.get((s, "upperleg")) for s in ("L", "R")]
    hips = None
    named = [j for j, (_, p, _, _) in enumerate(info) if p == "hips"]
    if all(x is not None for x in legs):
        above = [j for j in named if all(j in _ancestors(x, parents) for x in legs)]
        if above:
            hips = max(above, key=lambda j: _depth(j, parents))
            sm.why[hips] += "; above both legs: the hips"
        else:
            common = set(_ancestors(legs[0], parents)) & set(_ancestors(legs[1], parents))
            if common:
                hips = max(common, key=lambda j: _depth(j, parents))
                # skip pelvis-side joints shared by both legs? (none: they are per side)
                sm.why[hips] += "; the joint both legs branch from: the hips"
    elif named:
        hips = min(named, key=lambda j: _depth(j, parents))
        sm.why[hips] += "; named like the hips"
    if hips is not None:
        sm.bones[hips] = "root"

    # spine and neck: joints from the hips to the head
    head = [j for j, (_, p, _, _) in enumerate(info) if p == "head" and (hips is None or hips in _ancestors(j, parents))]
    head = min(head, key=lambda j: _depth(j, parents)) if head else None
    if head is not None:
        sm.bones[head] = "head"
    if hips is not None:
        if head is not None:
            chain = _path(hips, head, parents) or []
        else:  # no head: follow named spine/neck joints down from the hips
            chain, cur = [], hips
            while True:
                nxt = [k for k in kids[cur] if info[k][1] in ("spine", "neck")]
                if not nxt:
                    break
                cur = nxt[0]
                chain.append(cur)
        _map_trunk(sm, chain, hips, head, info, limb, parents, positions, anny_rest)

    if not _has_legs(sm):
        st = structural_map(names, parents, positions, anny_rest, first_frame)
        if st is not None:
            sm = st
    if explicit:
        _apply_explicit(sm, explicit)
    return sm


def _has_legs(sm: SkeletonMap) -> bool:
    b = set(sm.bones.values())
    return "root" in b and all(f"upperleg01.{s}" in b and ({f"lowerleg01.{s}", f"foot.{s}"} & b) for s in "LR")


def structural_map(names, parents, positions, anny_rest, first_frame=None) -> SkeletonMap | None:
    """A joint map from the skeleton's shape alone (for names that say nothing): the hips are the
    first joint from the root with two mirror branches (same number of joints, lengths within
    10 %: the legs) and a third whose subtree has another mirror pair (the arms, at the chest); in
    a leg the two longest consecutive segments are thigh and shin; in an arm, from the hand
    inwards, the last long segment is the forearm and the one before it the upper arm; the neck
    chain continues from the chest, its last joint the head. Left is the side the toes point
    left of (or the file's +x when there are no toes). None when no such shape is found."""
    parents = np.asarray(parents)
    J = len(names)
    kids = {j: [k for k in range(J) if parents[k] == j] for j in range(J)}
    seg = lambda a, b: float(np.linalg.norm(positions[a] - positions[b]))
    order = []
    stack = [j for j in range(J) if parents[j] < 0]
    while stack:
        j = stack.pop(0)
        order.append(j)
        stack.extend(kids[j])
    reach, size = np.zeros(J), np.ones(J, int)
    for j in reversed(order):
        if kids[j]:
            reach[j] = max(seg(j, k) + reach[k] for k in kids[j])
            size[j] = 1 + sum(size[k] for k in kids[j])

    def pair(h):
        best = None
        ks = kids[h]
        for i, a in enumerate(ks):
            for b in ks[i + 1:]:
                la, lb = seg(h, a) + reach[a], seg(h, b) + reach[b]
                if size[a] == size[b] >= 3 and abs(la - lb) <= 0.1 * max(la, lb) and la > 0:
                    if best is None or la > best[2]:
                        best = (a, b, la)
        return best[:2] if best else None

    def subtree(j):
        out, st = [], [j]
        while st:
            k = st.pop()
            out.append(k)
            st.extend(kids[k])
        return out

    def chain(j):  # j and its descendants along the longest reach
        out = [j]
        while kids[out[-1]]:
            out.append(max(kids[out[-1]], key=lambda k: seg(out[-1], k) + reach[k]))
        return out

    hips = legs = chest = arms = None
    for h in order:
        pr = pair(h)
        if pr and len(kids[h]) >= 3:
            up = max([k for k in kids[h] if k not in pr], key=lambda k: size[k])
            found = [x for x in sorted(subtree(up), key=order.index) if pair(x)]
            if found:
                hips, legs, chest, arms = h, pr, found[0], pair(found[0])
                break
    if hips is None:
        return None
    sm = SkeletonMap(list(names))
    for j in range(J):
        sm.why[j] = "structure: not a body bone"
    sm.bones[hips] = "root"
    sm.why[hips] = "structure (the names say nothing): the first joint with two mirror branches (the legs) and the spine"

    def limb(start, is_leg):
        c = chain(start)
        L = [seg(c[i], c[i + 1]) for i in range(len(c) - 1)]
        if len(L) < 2:
            return {}
        if is_leg:
            i = int(np.argmax([L[k] + L[k + 1] for k in range(len(L) - 1)]))
            parts = {"pelvis": c[i - 1] if i >= 1 else None, "upperleg": c[i], "lowerleg": c[i + 1],
                     "foot": c[i + 2] if i + 2 < len(c) else None, "toe": c[i + 3] if i + 3 < len(c) else None}
        else:
            long = [k for k in range(len(L)) if L[k] > 0.6 * max(L)]
            f = long[-1]
            if f < 1:
                return {}
            parts = {"clavicle": c[f - 2] if f >= 2 else None, "upperarm": c[f - 1], "forearm": c[f], "hand": c[f + 1]}
        return {k: v for k, v in parts.items() if v is not None}

    leg_parts = [limb(x, True) for x in legs]
    arm_parts = [limb(x, False) for x in arms]
    if not all("upperleg" in p and "lowerleg" in p for p in leg_parts):
        return None
    # sides, in a pose that stands
    pose = positions
    for cand in (positions, first_frame):
        if cand is None:
            continue
        up = cand[chest] - cand[hips]
        down = np.mean([cand[p.get("foot", p["lowerleg"])] for p in leg_parts], axis=0) - cand[hips]
        if np.dot(up, down) < -0.7 * np.linalg.norm(up) * np.linalg.norm(down):
            pose = cand
            break
    up = pose[chest] - pose[hips]
    up = up / (np.linalg.norm(up) or 1.0)
    toes = [p for p in leg_parts if "toe" in p and "foot" in p]
    if len(toes) == 2:
        fwd = np.mean([pose[p["toe"]] - pose[p["foot"]] for p in toes], axis=0)
        left, how = np.cross(up, fwd - np.dot(fwd, up) * up), "the toes point forward"
    else:
        left, how = np.array([1.0, 0, 0]) - up[0] * up, "no toes: the file's +x taken as the body's left"
    for group, plist, anchor in (("leg", leg_parts, "upperleg"), ("arm", arm_parts, "upperarm")):
        if len(plist) != 2 or not all(anchor in p for p in plist):
            continue
        base = hips if group == "leg" else chest
        a, b = (np.dot(pose[p[anchor]] - pose[base], left) for p in plist)
        for p, side in zip(plist, ("L", "R") if a >= b else ("R", "L")):
            for part, j in p.items():
                if part in _ANNY:
                    sm.bones[j] = f"{_ANNY[part]}.{side}"
                sm.why[j] = (f"structure: the {part} of one of the two mirror {group} branches; "
                             f"{'left' if side == 'L' else 'right'} because {how}")
    spine = _path(hips, chest, parents) or []
    for j in spine:
        sm.why[j] = "structure: spine joint"
    sm.bones[chest] = "spine01"
    sm.why[chest] = "structure: the arms branch from it: the upper chest"
    _by_fraction(sm, spine, hips, chest, "root", "spine01", _SPINE, positions, anny_rest, "structure: between hips and chest")
    rest = [k for k in kids[chest] if k not in arms]
    if rest:
        nk = chain(max(rest, key=lambda k: seg(chest, k) + reach[k]))
        # the chain may end at the head or above it (a head-top joint): Anny's head sits at a
        # third of a leg's length above the chest; a chain reaching past 0.42 legs has a top joint
        leg = np.mean([sum(seg(a, b) for a, b in zip(c, c[1:])) for c in
                       ([p[k] for k in ("upperleg", "lowerleg", "foot") if k in p] for p in leg_parts)])
        anny_leg = np.mean([np.linalg.norm(anny_rest[f"upperleg01.{x}"] - anny_rest[f"lowerleg01.{x}"]) +
                            np.linalg.norm(anny_rest[f"lowerleg01.{x}"] - anny_rest[f"foot.{x}"]) for x in "LR"])
        ratio = float(np.linalg.norm(anny_rest["head"] - anny_rest["spine01"]) / anny_leg)
        dist = np.cumsum([seg(chest, nk[0])] + [seg(a, b) for a, b in zip(nk, nk[1:])])
        if dist[-1] > 0.42 * leg and len(nk) > 1:
            h = int(np.argmin(np.abs(dist[:-1] - ratio * leg)))
            nk, why = nk[: h + 1], f"the joint nearest {ratio:.2f} leg lengths above the chest (the chain goes on to the top of the head)"
        else:
            why = "the end of the chain above the chest"
        sm.bones[nk[-1]] = "head"
        sm.why[nk[-1]] = f"structure: {why}: the head"
        for j in nk[1:-1]:
            sm.why[j] = "structure: neck joint"
        if len(nk) > 1:
            sm.bones[nk[0]] = "neck01"
            sm.why[nk[0]] = "structure: the first joint above the chest: the neck"
            _by_fraction(sm, nk[1:-1], nk[0], nk[-1], "neck01", "head", _NECK[1:], positions, anny_rest,
                         "structure: between neck and head")
    return sm


def _map_trunk(sm, chain, hips, head, info, limb, parents, positions, anny_rest):
    names = sm.names
    necks = [j for j in chain if info[j][1] == "neck"]
    first_neck = necks[0] if necks else (head if head is not None else None)
    spine = chain[: chain.index(first_neck)] if first_neck in chain else list(chain)
    neck = chain[chain.index(first_neck):] if first_neck in chain else []
    arms = [limb.get((s, p)) for s in ("L", "R") for p in ("clavicle", "upperarm")]
    arms = [a for a in arms if a is not None]
    chest = None
    for a in arms:  # the spine joint the arms branch from
        anc = [k for k in _ancestors(a, parents) if k in spine]
        if anc:
            chest = anc[0] if chest is None else max(chest, anc[0], key=lambda k: spine.index(k))
    how = "the arms branch from it"
    if chest is None and spine:
        chest, how = spine[-1], "the last spine joint below the neck"
    if chest is not None:
        sm.bones[chest] = "spine01"
        sm.why[chest] += f"; {how}: the upper chest"
        lower = spine[: spine.index(chest)]
        _by_fraction(sm, lower, hips, chest, "root", "spine01", _SPINE, positions, anny_rest,
                     f"between the hips {names[hips]!r} and the chest {names[chest]!r}")
        for k in spine[spine.index(chest) + 1:]:
            sm.why[k] += "; spine joint above the chest: left unmapped"
    if neck:
        sm.bones[neck[0]] = "neck01"
        sm.why[neck[0]] += "; the first neck joint"
        if head is not None:
            _by_fraction(sm, neck[1:], neck[0], head, "neck01", "head", _NECK[1:], positions, anny_rest,
                         f"between {names[neck[0]]!r} and the head")


def _by_fraction(sm, joints, a, b, anny_a, anny_b, anny_bones, positions, anny_rest, where):
    """Map joints on the chain a..b to Anny bones on anny_a..anny_b at the nearest fraction of the
    length, in order, each bone once."""
    if not joints:
        return
    pts = [a] + list(joints) + [b]
    steps = [float(np.linalg.norm(positions[pts[i + 1]] - positions[pts[i]])) for i in range(len(pts) - 1)]
    total = sum(steps) or 1.0
    fr = np.cumsum(steps)[:-1] / total
    ha, hb = anny_rest[anny_a], anny_rest[anny_b]
    L = float(np.linalg.norm(hb - ha)) or 1.0
    afr = {n: float(np.dot(anny_rest[n] - ha, (hb - ha) / L) / L) for n in anny_bones}
    free = list(anny_bones)
    for j, f in zip(joints, fr):
        if not free:
            sm.why[j] += f"; {where}: no Anny bone left, unmapped"
            continue
        best = min(free, key=lambda n: abs(afr[n] - f))
        free = free[free.index(best) + 1:]  # keep the order along the chain
        sm.bones[j] = best
        sm.why[j] += f"; {where} at {100 * f:.0f}% of the length: Anny's {best} is at {100 * afr[best]:.0f}%"


def _apply_explicit(sm: SkeletonMap, explicit: dict[str, str]) -> None:
    lookup = {}
    for j, n in enumerate(sm.names):
        lookup.setdefault(n, j)
        lookup.setdefault(re.split(r"[:|]", n)[-1], j)
    missing = [k for k in explicit if k not in lookup]
    if missing:
        raise KeyError(f"the mapping names joints the skeleton lacks: {missing}")
    for k, bone in explicit.items():
        j = lookup[k]
        if bone:
            for other in [o for o, b in sm.bones.items() if b == bone and o != j]:
                del sm.bones[other]
                sm.why[other] += f"; un-mapped: the mapping gives {bone} to {k!r}"
            sm.bones[j] = bone
        else:
            sm.bones.pop(j, None)
        sm.why[j] = f"mapping file: {bone or 'unmapped'}"
