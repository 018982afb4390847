"""The site's Zenoh access control: which process (certificate common name) may send what.

Every process of a site runs the same ``access_control`` section (Zenoh 1.x ACL: rules,
subjects matched by ``cert_common_names`` of the mutual-TLS peer, policies; default deny).
Each process checks what arrives on its links (``ingress``); what it sends (``egress``) and
the declarations that let routing work (subscribers, queryables, liveliness subscribers and
queries) are allowed. Data, queries, replies and liveliness tokens arriving are allowed only:

| sender CN | may put | may query | may reply on | liveliness token |
|---|---|---|---|---|
| server | machine/*/sim/reset, runtime/*/estop | runtime/*/{throw,abort,estop_reset,return_to_ready,info,policy/offer,lease} | server/throw_result, server/policy/* | - |
| runtime-<id> | machine/<id>/{valve_cmd,gripper_cmd}, runtime/<id>/{status,runtime_state,policy/status,estop_ack} | server/throw_result, server/policy/* | runtime/<id>/{throw,abort,estop_reset,return_to_ready,info,policy/offer,lease} | runtime/<id>/{alive,claim/*} |
| plant-<id> | machine/<id>/{state,impact} | - | - | machine/<id>/{alive,claim/*} |
| router | everything (it forwards; it enforces these rules itself on its own links) |

(all keys under ``slinger/``). A peer with a certificate of another role is denied on ingress
by the receiving process; a peer without a site certificate cannot open a TLS link at all.
Commands are also signed (runtime.command_auth): the ACL keeps forged traffic off the links,
the signatures keep a compromised or misconfigured link from commanding a throw.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from runtime.protocol import keys

DATA = ("put", "delete", "query", "reply", "liveliness_token")
DECLARATIONS = ("declare_subscriber", "declare_queryable", "declare_liveliness_subscriber", "liveliness_query")
RUNTIME_QUERYABLES = ("throw", "abort", "estop_reset", "return_to_ready", "info", "policy/offer", "lease")


def _rule(rule_id: str, messages: Sequence[str], key_exprs: Sequence[str], flows: Sequence[str] = ("ingress",)) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": list(flows), "messages": list(messages), "key_exprs": list(key_exprs)}


def machines_in_site(site_dir: str | Path) -> list[str]:
    """Machine ids of a site directory: those with ``machines/<id>/command.key`` (sorted)."""
    root = Path(site_dir) / "machines"
    return sorted(p.parent.name for p in root.glob("*/command.key")) if root.is_dir() else []


def site_acl(machine_ids: Sequence[str]) -> dict:
    """The ``access_control`` section for a site with ``machine_ids`` (see the module table).

    Raises:
        ValueError: a bad machine id.
    """
    server_results = [keys.THROW_RESULT, keys.POLICY_FILES]
    rules = [
        _rule("egress", (*DATA, *DECLARATIONS), ["**"], ("egress",)),
        _rule("declarations", DECLARATIONS, ["**"]),
        _rule("router", DATA, ["**"]),
        _rule("server-put", ["put"], [f"{keys.ROOT}/machine/*/sim/reset", f"{keys.ROOT}/runtime/*/estop"]),
        _rule("server-query", ["query"], [f"{keys.ROOT}/runtime/*/{leaf}" for leaf in RUNTIME_QUERYABLES]),
        _rule("server-reply", ["reply"], server_results),
    ]
    subjects = [
        {"id": "anyone"},
        {"id": "router", "cert_common_names": ["router"]},
        {"id": "server", "cert_common_names": ["server"]},
    ]
    policies = [
        {"id": "all", "rules": ["egress", "declarations"], "subjects": ["anyone"]},
        {"id": "router", "rules": ["router"], "subjects": ["router"]},
        {"id": "server", "rules": ["server-put", "server-query", "server-reply"], "subjects": ["server"]},
    ]
    for mid in dict.fromkeys(keys.validate_machine_id(m) for m in machine_ids):
        rt, pl = f"runtime-{mid}", f"plant-{mid}"
        rules += [
            _rule(f"{rt}-put", ["put"], [keys.valve_cmd(mid), keys.gripper_cmd(mid), keys.status(mid),
                                         keys.runtime_state(mid), keys.policy_status(mid), keys.estop_ack(mid)]),
            _rule(f"{rt}-query", ["query"], server_results),
            _rule(f"{rt}-reply", ["reply"], [keys.runtime(mid, leaf) for leaf in RUNTIME_QUERYABLES]),
            _rule(f"{rt}-token", ["liveliness_token"], [keys.runtime_alive(mid), keys.runtime_claim(mid, "*")]),
            _rule(f"{pl}-put", ["put"], [keys.state(mid), keys.impact(mid)]),
            _rule(f"{pl}-token", ["liveliness_token"], [keys.machine_alive(mid), keys.machine_claim(mid, "*")]),
        ]
        subjects += [{"id": rt, "cert_common_names": [rt]}, {"id": pl, "cert_common_names": [pl]}]
        policies += [
            {"id": rt, "rules": [f"{rt}-put", f"{rt}-query", f"{rt}-reply", f"{rt}-token"], "subjects": [rt]},
            {"id": pl, "rules": [f"{pl}-put", f"{pl}-token"], "subjects": [pl]},
        ]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
