// btcpp_check: load a btmission BehaviorTree.CPP XML export in real BehaviorTree.CPP 4.x.
//
//   btcpp_check FILE.xml [MAX_TICKS]
//
// 1. Registers every <Action>/<Condition> of the file's <TreeNodesModel> as a dummy node with
//    the declared ports (no TreeNodesModel, or a model without ID, is a failure).
// 2. Runs BT::VerifyXML, then BehaviorTreeFactory::createTreeFromText (main_tree_to_execute).
// 3. Puts every blackboard key the trees reference ("{key}") into the root blackboard, reads
//    every input port of every node of the created tree (subtrees included) with getInput,
//    and ticks the tree until it stops RUNNING, at most MAX_TICKS times (default 1000).
//    Dummy conditions fail on their first tick and succeed afterwards; dummy actions return
//    RUNNING on their first tick and SUCCESS on the next, so reactive halting is exercised.
//
// Prints one line, "OK: ..." or "FAIL: FILE: <error>", and exits 0 or 1 (2 for bad usage).

#include <behaviortree_cpp/bt_factory.h>
#include <behaviortree_cpp/xml_parsing.h>
#include <tinyxml2.h>

#include <cstdlib>
#include <fstream>
#include <iostream>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace
{

struct Model
{
  BT::NodeType type;
  std::string id;
  BT::PortsList ports;
};

// Counters shared by all dummy nodes of one run.
struct Stats
{
  std::size_t leaf_ticks = 0;
  std::set<std::string> ticked;  // registration IDs that were ticked at least once
};

class DummyCondition : public BT::ConditionNode
{
public:
  DummyCondition(const std::string& name, const BT::NodeConfig& config, Stats& stats)
    : BT::ConditionNode(name, config), stats_(stats)
  {}

  BT::NodeStatus tick() override
  {
    ++stats_.leaf_ticks;
    stats_.ticked.insert(registrationName());
    return ticks_++ == 0 ? BT::NodeStatus::FAILURE : BT::NodeStatus::SUCCESS;
  }

private:
  Stats& stats_;
  int ticks_ = 0;
};

class DummyAction : public BT::StatefulActionNode
{
public:
  DummyAction(const std::string& name, const BT::NodeConfig& config, Stats& stats)
    : BT::StatefulActionNode(name, config), stats_(stats)
  {}

  BT::NodeStatus onStart() override
  {
    ++stats_.leaf_ticks;
    stats_.ticked.insert(registrationName());
    return BT::NodeStatus::RUNNING;
  }

  BT::NodeStatus onRunning() override
  {
    ++stats_.leaf_ticks;
    return BT::NodeStatus::SUCCESS;
  }

  void onHalted() override {}

private:
  Stats& stats_;
};

std::string readFile(const std::string& path)
{
  std::ifstream in(path, std::ios::binary);
  if(!in)
  {
    throw std::runtime_error("cannot read the file");
  }
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

// The <TreeNodesModel> entries (actions and conditions), and every "{key}" attribute value
// used inside the <BehaviorTree> elements.
void scan(const std::string& xml, std::vector<Model>& models, std::set<std::string>& keys)
{
  tinyxml2::XMLDocument doc;
  if(doc.Parse(xml.c_str(), xml.size()) != tinyxml2::XML_SUCCESS)
  {
    throw std::runtime_error(std::string("not well-formed XML: ") + doc.ErrorStr());
  }
  const tinyxml2::XMLElement* root = doc.RootElement();
  const tinyxml2::XMLElement* model_root =
      root != nullptr ? root->FirstChildElement("TreeNodesModel") : nullptr;
  if(model_root == nullptr)
  {
    throw std::runtime_error("no <TreeNodesModel>");
  }
  for(auto* m = model_root->FirstChildElement(); m != nullptr; m = m->NextSiblingElement())
  {
    const std::string tag = m->Name();
    if(tag != "Action" && tag != "Condition")
    {
      throw std::runtime_error("unexpected <" + tag + "> in <TreeNodesModel>");
    }
    const char* id = m->Attribute("ID");
    if(id == nullptr)
    {
      throw std::runtime_error("<" + tag + "> without ID in <TreeNodesModel>");
    }
    Model model{ tag == "Action" ? BT::NodeType::ACTION : BT::NodeType::CONDITION, id, {} };
    for(auto* p = m->FirstChildElement(); p != nullptr; p = p->NextSiblingElement())
    {
      const std::string ptag = p->Name();
      const char* pname = p->Attribute("name");
      if(ptag == "input_port" && pname != nullptr)
      {
        model.ports.insert(BT::InputPort<std::string>(pname));
      }
      else if(ptag != "description")
      {
        throw std::runtime_error("unexpected <" + ptag + "> in the model of " + model.id);
      }
    }
    models.push_back(model);
  }
  // Iterative walk of every <BehaviorTree> (the files may be thousands of levels deep).
  std::vector<const tinyxml2::XMLElement*> stack;
  for(auto* t = root->FirstChildElement("BehaviorTree"); t != nullptr;
      t = t->NextSiblingElement("BehaviorTree"))
  {
    stack.push_back(t);
  }
  while(!stack.empty())
  {
    const tinyxml2::XMLElement* e = stack.back();
    stack.pop_back();
    for(auto* a = e->FirstAttribute(); a != nullptr; a = a->Next())
    {
      const std::string v = a->Value();
      if(v.size() >= 2 && v.front() == '{' && v.back() == '}')
      {
        keys.insert(v.substr(1, v.size() - 2));
      }
    }
    for(auto* c = e->FirstChildElement(); c != nullptr; c = c->NextSiblingElement())
    {
      stack.push_back(c);
    }
  }
}

}  // namespace

int main(int argc, char** argv)
{
  if(argc < 2 || argc > 3)
  {
    std::cerr << "usage: btcpp_check FILE.xml [MAX_TICKS]\n";
    return 2;
  }
  const std::string path = argv[1];
  long max_ticks = 1000;
  if(argc == 3)
  {
    char* end = nullptr;
    max_ticks = std::strtol(argv[2], &end, 10);
    if(end == argv[2] || *end != '\0' || max_ticks < 1)
    {
      std::cerr << "btcpp_check: MAX_TICKS must be a positive integer, not '" << argv[2]
                << "'\n";
      return 2;
    }
  }
  try
  {
    const std::string xml = readFile(path);
    std::vector<Model> models;
    std::set<std::string> keys;
    scan(xml, models, keys);

    Stats stats;
    BT::BehaviorTreeFactory factory;
    for(const Model& model : models)
    {
      BT::TreeNodeManifest manifest{ model.type, model.id, model.ports, {} };
      if(model.type == BT::NodeType::ACTION)
      {
        factory.registerBuilder(manifest, [&stats](const std::string& name,
                                                   const BT::NodeConfig& config) {
          return std::make_unique<DummyAction>(name, config, stats);
        });
      }
      else
      {
        factory.registerBuilder(manifest, [&stats](const std::string& name,
                                                   const BT::NodeConfig& config) {
          return std::make_unique<DummyCondition>(name, config, stats);
        });
      }
    }

    std::unordered_map<std::string, BT::NodeType> registered;
    for(const auto& [id, manifest] : factory.manifests())
    {
      registered.insert({ id, manifest.type });
    }
    BT::VerifyXML(xml, registered);

    auto blackboard = BT::Blackboard::create();
    for(const std::string& key : keys)
    {
      blackboard->set<std::string>(key, "value of " + key);
    }
    BT::Tree tree = factory.createTreeFromText(xml, blackboard);

    std::size_t nodes = 0;
    for(const auto& subtree : tree.subtrees)
    {
      for(const auto& node : subtree->nodes)
      {
        ++nodes;
        const BT::TreeNode& leaf = *node;
        for(const auto& [port, info] : leaf.config().input_ports)
        {
          (void)info;
          const auto value = node->getInput<std::string>(port);
          if(!value)
          {
            throw std::runtime_error("node '" + node->fullPath() + "': input port '" + port +
                                     "': " + value.error());
          }
        }
      }
    }

    BT::NodeStatus status = BT::NodeStatus::RUNNING;
    long ticks = 0;
    while(status == BT::NodeStatus::RUNNING && ticks < max_ticks)
    {
      status = tree.tickOnce();
      ++ticks;
    }
    if(status == BT::NodeStatus::RUNNING)
    {
      throw std::runtime_error("still RUNNING after " + std::to_string(ticks) + " ticks");
    }
    tree.haltTree();

    std::cout << "OK: " << path << ": BehaviorTree.CPP " << BT::LibraryVersionString() << ", "
              << models.size() << " node models, " << tree.subtrees.size() << " (sub)trees, "
              << nodes << " nodes, " << keys.size() << " blackboard keys; " << ticks
              << " ticks -> " << BT::toStr(status) << ", " << stats.leaf_ticks
              << " leaf ticks, " << stats.ticked.size() << " node types ticked\n";
    return 0;
  }
  catch(const std::exception& error)
  {
    std::string message = error.what();
    for(char& c : message)
    {
      if(c == '\n')
      {
        c = ' ';
      }
    }
    std::cout << "FAIL: " << path << ": " << message << "\n";
    return 1;
  }
}
